"""centroids' ``sum-indirect.exr``: the sum of the beam frames, each without its own spot's
disc, which build-isf's silhouette test judges a pixel's share on (docs/spots-and-isf.md)."""

import numpy as np

from ilt.io.exr import read_exr, write_exr
from ilt.spots.stage import INDIRECT_SUM_FILE, SPOT_SIGMAS, SUM_FILE, run_centroids


def test_the_indirect_sum_is_the_sum_without_each_frames_own_spot(tmp_path):
    """Four frames, each a Gaussian spot (sigma 1.5 px) on an indirect light that varies
    over the frame: far from every spot the two sums are the same; within 2.5 sigma of a
    spot their difference is that spot's frame there, and only its own; and whatever is
    taken is inside SPOT_SIGMAS sigma of a spot."""
    height, width, sigma = 48, 64, 1.5
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    (tmp_path / "hdr").mkdir()
    centres = [(12.3, 10.6), (40.2, 12.1), (20.7, 35.4), (50.5, 36.8)]
    frames = []
    for k, (x, y) in enumerate(centres):
        indirect = 0.02 * (1 + k) * (1 + xx / width)
        frame = indirect + 50.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))
        frames.append(frame)
        write_exr(tmp_path / "hdr" / f"beam-{k:05d}.exr", frame.astype(np.float32), ["Y"])
    run_centroids(tmp_path / "hdr", tmp_path / "spots", workers=1)
    total = read_exr(tmp_path / "spots" / SUM_FILE)[0][..., 0].astype(np.float64)
    indirect = read_exr(tmp_path / "spots" / INDIRECT_SUM_FILE)[0][..., 0].astype(np.float64)
    distance = np.stack([np.hypot(xx - x, yy - y) for x, y in centres])       # (4, H, W)
    far = distance.min(axis=0) > SPOT_SIGMAS * sigma + 1.5
    np.testing.assert_allclose(indirect[far], total[far], rtol=1e-6)
    taken = total - indirect
    for k in range(len(centres)):
        near = distance[k] < 2.5 * sigma
        np.testing.assert_allclose(taken[near], frames[k][near], rtol=1e-5)
    assert np.all(np.abs(taken[distance.min(axis=0) > SPOT_SIGMAS * sigma + 1.5]) < 1e-5)
    assert indirect.min() > 0.0
