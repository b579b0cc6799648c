"""Isolated outlier pixels (fireflies, hot pixels) replaced before the cell sums (ilt.isf.outliers)."""

import json
import re
import shutil

import numpy as np
import pytest

from ilt.io.exr import read_exr, write_exr
from ilt.isf.build import build_isf
from ilt.isf.noise import FrameNoise
from ilt.isf.outliers import OUTLIER_SIGMAS, clamp_isolated

GAIN = 2.0     # electrons per unit: Var = X / GAIN + READ^2
READ = 0.5
NOISE = FrameNoise((0.0, 1e4), (READ**2, READ**2 + 1e4 / GAIN), 8, 10**6, 2, 1.0 / GAIN)


def _scene(rng, shape=(300, 400)):
    """Smooth light with photon and read noise, a laser spot (sigma 0.8 px) at (100, 150),
    and a bright line one pixel wide along row 250: light, not outliers."""
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    clean = 40.0 + 30.0 * np.exp(-((x - 250) ** 2 + (y - 120) ** 2) / (2 * 80.0**2))
    clean += 5e4 * np.exp(-((x - 100) ** 2 + (y - 150) ** 2) / (2 * 0.8**2))
    clean[250, 50:350] += 400.0
    noisy = rng.poisson(clean * GAIN) / GAIN + rng.normal(0, READ, shape)
    return clean, noisy


def test_fireflies_are_replaced_and_light_is_not():
    """60 fireflies (10-200x the light) away from the spot are all replaced, each by a value
    within 5 sigma of the clean light there; no other pixel changes: not the noise (120000
    pixels at OUTLIER_SIGMAS), not the spot's peak, not the one-pixel line."""
    rng = np.random.default_rng(11)
    clean, frame = _scene(rng)
    before = frame.copy()
    spots = np.argwhere(np.hypot(*(np.mgrid[:300, :400] - np.array([150, 100])[:, None, None])) > 20)
    spots = spots[(np.abs(spots[:, 0] - 250) > 1) & (spots[:, 0] > 0) & (spots[:, 0] < 299)]
    hits = spots[rng.choice(len(spots), 60, replace=False)]        # (none touch: checked below)
    assert np.abs(hits[:, None, :] - hits[None]).max(axis=2)[~np.eye(60, dtype=bool)].min() > 1
    frame[hits[:, 0], hits[:, 1]] += clean[hits[:, 0], hits[:, 1]] * rng.uniform(10, 200, 60)
    count = clamp_isolated(frame, NOISE, np.array([100.0, 150.0]), 10.0)
    assert count == 60
    changed = np.argwhere(frame != before)
    assert sorted(map(tuple, changed)) == sorted(map(tuple, hits))
    sigma = np.sqrt(NOISE.pixel_variance(clean[hits[:, 0], hits[:, 1]]))
    assert np.all(np.abs(frame[hits[:, 0], hits[:, 1]] - clean[hits[:, 0], hits[:, 1]]) < 5 * sigma)


def test_photon_counts_are_judged_on_their_own_scale():
    """Photon noise alone (a path tracer's, or counts without read noise): most pixels count
    no photon, and the model's variance at their level is 0. A pixel of 1-6 photons among
    none is noise (none of 200000 is touched); one of 200 photons among none is a firefly."""
    rng = np.random.default_rng(13)
    quantum = 0.2                                        # frame units per photon
    counts = FrameNoise((0.0, 0.01, 10.0), (0.0, 0.0, 10.0 * quantum), 8, 10**6, 3, quantum)
    frame = rng.poisson(0.3, (400, 500)) * quantum
    before = frame.copy()
    assert clamp_isolated(frame, counts) == 0
    np.testing.assert_array_equal(frame, before)
    around = frame[199:202, 249:252]
    around[around > 2 * quantum] = 0.0                  # its neighbours: none above 2 photons
    frame[200, 250] = 200 * quantum
    assert clamp_isolated(frame, counts) == 1 and frame[200, 250] <= 2 * quantum


def test_a_screening_model_drops_the_bright_knots_fireflies_inflate():
    """Photon noise (Var = 0.2 x) fitted with its two brightest bins inflated 50x: the
    screening model keeps the 8 faint knots of 10 and extends them with their own slope."""
    from ilt.isf.outliers import screening_model

    levels = tuple(float(x) for x in range(10))
    variances = tuple(0.2 * x * (50.0 if x >= 8 else 1.0) for x in levels)
    fitted = FrameNoise(levels, variances, 8, 10**5, 10, 40.0)
    screen = screening_model(fitted)
    assert screen.levels == levels[:8] and screen.slope == pytest.approx(0.2)
    assert screen.pixel_variance(np.array([20.0]))[0] == pytest.approx(4.0)


def test_the_spot_window_and_frames_without_a_noise_model_are_left_alone():
    rng = np.random.default_rng(12)
    _, frame = _scene(rng)
    frame[150, 104] += 1e4               # within the spot's window
    before = frame.copy()
    assert clamp_isolated(frame, NOISE, np.array([100.0, 150.0]), 10.0) == 0
    np.testing.assert_array_equal(frame, before)
    frame[20, 20] += 1e4
    assert clamp_isolated(frame, None) == 0 and frame[20, 20] == before[20, 20] + 1e4
    assert clamp_isolated(frame, NOISE) >= 1 and OUTLIER_SIGMAS == 6.0


def test_build_isf_replaces_fireflies_before_the_cell_sums(tmp_path, monkeypatch):
    """A simulated noisy scan, and the same frames with 1e-3 of their pixels raised 20x the
    frame's 99.9th percentile (times an exponential draw): T built from the second is the
    first's to within a fifth of each entry's own noise (T_var) at 99% of its entries (the
    rest: two fireflies side by side, not isolated), and the manifest counts 97% of the
    fireflies. Without the replacement the fireflies moved a tenth of T's entries by more
    than 10 sigma (and the reciprocity test called the scan not Lambertian)."""
    import ilt.isf.build as build
    from tests.isf.test_build import run
    from tests.isf.test_noise import _noisy

    sim, noisy, fire = tmp_path / "sim", tmp_path / "noisy", tmp_path / "fire"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 12, "-o", sim)
    rng = np.random.default_rng(3)
    frames = sorted((sim / "hdr").glob("beam-*.exr"))
    gain = 2e4 / max(float(read_exr(f)[0].max()) for f in frames)
    shutil.copytree(sim / "hdr", noisy)
    shutil.copytree(sim / "hdr", fire)
    injected = 0
    for f in frames:
        image, attributes = read_exr(f)
        kept = {k: v for k, v in attributes.items() if k.startswith("ilt:")}
        frame = _noisy(image.astype(np.float64), gain, rng)
        write_exr(noisy / f.name, frame.astype(np.float32), ["Y"], kept)
        y = frame[..., 0]
        hits = rng.choice(y.size, max(1, int(1e-3 * y.size)), replace=False)
        y.flat[hits] += 20 * np.quantile(y, 0.999) * rng.exponential(1.0, hits.size)
        injected += hits.size
        write_exr(fire / f.name, frame.astype(np.float32), ["Y"], kept)
    run("centroids", noisy, "-o", tmp_path / "spots", "--workers", 1)
    # the same cells for all three (the folds' barriers, read from each scan's light, would
    # differ by its noise): what differs is the T pass
    build_isf(noisy, tmp_path / "spots", tmp_path / "a", workers=1, fold_cells=False)
    build_isf(fire, tmp_path / "spots", tmp_path / "b", workers=1, fold_cells=False)
    monkeypatch.setattr(build, "clamp_isolated", lambda *args, **kwargs: 0)
    build_isf(fire, tmp_path / "spots", tmp_path / "c", workers=1, lambertian=False, fold_cells=False)
    a, b, c = (np.load(tmp_path / d / "T.npy") * np.load(tmp_path / d / "scales.npy") for d in ("a", "b", "c"))
    sigma = np.sqrt(np.load(tmp_path / "a" / "T_var.npy")) * np.load(tmp_path / "a" / "scales.npy")[None, :]
    assert np.quantile(np.abs(b - a) / sigma, 0.99) < 0.2
    assert np.quantile(np.abs(c - a) / sigma, 0.9) > 10
    outliers = json.loads((tmp_path / "b" / "manifest.json").read_text())["outliers"]
    assert 0.97 * injected <= outliers["pixels"] <= injected
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["outliers"]["pixels"] == 0
    # the folds' far light: 1e-3 of each frame's pixels fresh fireflies, 0.032 of the sum's,
    # side by side there: read from the frames, each with its own replaced
    monkeypatch.undo()
    build_isf(fire, tmp_path / "spots", tmp_path / "d", workers=1, lambertian=False)
    folds = json.loads((tmp_path / "d" / "manifest.json").read_text())["folds"]
    share = re.fullmatch(r"a pass over the frames \(outliers in (\S+) of each frame's pixels\), "
                         r"each frame's stripe across the spots' line left out", folds["far_light"])
    assert share and 0.0008 < float(share.group(1)) <= 0.001


def test_fresh_outliers_count_fireflies_not_hot_pixels():
    """Outliers at pixels of their own in each frame (fireflies) are counted per frame; one
    at the same pixel of every frame (a hot pixel) is not."""
    from ilt.isf.outliers import fresh_outliers

    hot = [[5, 9], [5, 9], [5, 9, 40], [9, 5]]
    assert fresh_outliers(hot, 1000) == pytest.approx((3 - 2.25) / 3 / 1000)
    fireflies = [[1, 2], [3, 4], [5, 6], [7, 8]]
    assert fresh_outliers(fireflies, 1000) == pytest.approx(2 / 1000)
    assert fresh_outliers([[], []], 1000) == 0.0 and fresh_outliers([[3, 4]], 100) == 0.02
