"""The frames' noise read off their sum, carried into T's entries and used by the fine fit's test (issue 21)."""

import json
import shutil

import numpy as np
import pytest

from ilt.io.exr import read_exr, write_exr
from ilt.isf.build import build_isf
from ilt.isf.directory import load_isf
from ilt.isf.fine import MIN_EXPLAINED, CellGeometry, FineAccumulator, fit_operator
from ilt.isf.noise import NOISE_FILE, FrameNoise, fit_frame_noise, read_noise

READ_E = 3.0


def _smooth_field(shape=(160, 200)):
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    field = 800.0 * np.exp(-((x - 120) ** 2 + (y - 70) ** 2) / (2 * 45.0**2)) + 1.0 * x
    field[:40, :40] = 0.0          # a dark corner, as a scan's background: its noise reads below zero
    return field


def _noisy(image, gain, rng, read=READ_E):
    return (rng.poisson(np.maximum(image, 0) * gain) + rng.normal(0, read, image.shape)) / gain


@pytest.mark.parametrize("gain", [2.0, 20.0])
def test_the_frames_noise_is_read_off_their_sum(gain):
    """The sum of m frames with photon noise (gain e- per unit) and read noise (READ_E
    e-) has Var = m (READ_E / gain)^2 + S / gain: the fit gives both per frame, with
    sharp spots in the sum (left out around their centroids) and a noise-free sum none.
    The sum's light reaches several times its read noise's variance, so that the slope
    is measurable (where S / gain stays below m a, b is known to no better than 2x)."""
    rng = np.random.default_rng(1)
    m = 40
    truth = _smooth_field()
    spots = np.array([[30.5, 40.2], [150.0, 120.7], [90.3, 20.0]])
    y, x = np.mgrid[:truth.shape[0], :truth.shape[1]]
    for cx, cy in spots:
        truth = truth + 8000.0 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 2.0)
    S = sum(_noisy(truth / m, gain, rng) for _ in range(m))
    fit = fit_frame_noise(S, m, spots)
    assert fit.a == pytest.approx((READ_E / gain) ** 2, rel=0.05)
    assert fit.b == pytest.approx(1.0 / gain, rel=0.15)
    assert fit_frame_noise(truth, m, spots) is None


def test_cell_variance_is_the_sum_over_the_cells_pixels():
    """Var of a cell sum of n pixels with Var = a + b X each: a n + b (cell sum)."""
    rng = np.random.default_rng(2)
    noise = FrameNoise(a=(READ_E / 5.0) ** 2, b=1 / 5.0, beams=1, pixels=0, bins=0)
    signal = rng.uniform(0, 30, size=(3, 50))      # 3 cells of 50 pixels
    draws = np.stack([_noisy(signal, 5.0, rng).sum(axis=1) for _ in range(4000)])
    predicted = noise.cell_variance(signal.sum(axis=1)[:, None], np.full(3, 50.0))[:, 0]
    np.testing.assert_allclose(draws.var(axis=0), predicted, rtol=0.08)


def test_build_isf_carries_the_noise_into_t_and_decompose_uses_it(tmp_path):
    """noise.json's entry_sigma is the RMS of the noise in T's unit-column entries: built
    on the same cells from noisy and noise-free frames, T differs by about that much;
    decompose takes it as T's noise, and says where it came from."""
    from tests.isf.test_build import run

    sim, noisy = tmp_path / "sim", tmp_path / "noisy"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 12, "-o", sim)
    rng = np.random.default_rng(3)
    frames = sorted((sim / "hdr").glob("beam-*.exr"))
    gain = 2e4 / max(float(read_exr(f)[0].max()) for f in frames)
    shutil.copytree(sim / "hdr", noisy)
    for f in frames:
        image, attributes = read_exr(f)
        write_exr(noisy / f.name, _noisy(image.astype(np.float64), gain, rng).astype(np.float32), ["Y"],
                  {k: v for k, v in attributes.items() if k.startswith("ilt:")})
    run("centroids", noisy, "-o", tmp_path / "spots", "--workers", 1)
    build_isf(noisy, tmp_path / "spots", tmp_path / "isf", workers=1)
    build_isf(sim / "hdr", tmp_path / "spots", tmp_path / "clean", workers=1, fine_degree=None)
    record = read_noise(tmp_path / "isf")
    assert record["a"] == pytest.approx((READ_E / gain) ** 2, rel=0.1)
    a, b = load_isf(tmp_path / "isf"), load_isf(tmp_path / "clean")
    assert (a.cells == b.cells).all()
    scales = np.load(tmp_path / "isf" / "scales.npy")
    difference = (a.T * scales - b.T * np.load(tmp_path / "clean" / "scales.npy")) / scales
    assert record["entry_sigma"] == pytest.approx(float(np.sqrt(np.mean(difference**2))), rel=0.2)
    assert json.loads((tmp_path / "isf" / "manifest.json").read_text())["outputs"].get(NOISE_FILE)

    run("decompose", "--isf", tmp_path / "isf", sim / "photos" / "room.exr", "-o", tmp_path / "dec", "--no-cache")
    summary = json.loads((tmp_path / "dec" / "room" / "summary.json").read_text())
    operator = summary["operators"]
    assert operator["noise"] == pytest.approx(record["entry_sigma"])
    assert NOISE_FILE in operator["noise_source"]


def _two_cells(rng, slope, pixel_sigma):
    """Cells 0 and 1, the left and right halves of a 24 x 48 px frame, each a beam's own:
    beam 0 puts into cell 1 a field ``slope`` x (x - its centre) + 5, beam 1 a constant
    into cell 0, both with per-pixel noise ``pixel_sigma``. Returns the accumulator."""
    labels = np.zeros((24, 48), np.int64)
    labels[:, 24:] = 1
    geometry = CellGeometry.from_labels(labels, 2)
    fit = fit_operator(geometry, 1)
    noise = FrameNoise(a=pixel_sigma**2, b=0.0, beams=1, pixels=0, bins=0) if pixel_sigma else None
    acc = FineAccumulator(np.zeros((2, 2, 2), np.float32), geometry, 1, noise)
    x = np.arange(48.0)[None, :].repeat(24, axis=0)
    frames = np.stack([np.where(labels == 1, 5.0 + slope * (x - 35.5), 50.0), np.full(labels.shape, 5.0)])
    frames = frames + rng.normal(0, pixel_sigma, frames.shape)
    flat = [f.ravel() for f in frames]
    coefficients = np.stack([fit @ f for f in flat], axis=-1).reshape(2, 2, 2)
    raw = np.stack([np.bincount(labels.ravel(), f, 2) for f in flat], axis=1)
    squares = np.stack([np.bincount(labels.ravel(), f**2, 2) for f in flat], axis=1)
    acc.add(0, coefficients, raw, squares, np.ones(2))
    return acc


def test_the_fine_fit_tells_a_slope_from_noise():
    """A sloped cell under noise as large as its light's variation keeps its slope when
    the test knows the noise (the old 90%-explained rule made it flat); a flat cell's fit
    of noise alone is kept flat; noise-free, the shares are as before."""
    rng = np.random.default_rng(4)
    known = _two_cells(rng, slope=0.3, pixel_sigma=1.0).finish()
    assert known[1] >= MIN_EXPLAINED and known[0] < MIN_EXPLAINED
    rng = np.random.default_rng(4)
    unknown = _two_cells(rng, slope=0.3, pixel_sigma=1.0)
    unknown.noise = None
    unknown.noise_explained[:] = unknown.noise_total[:] = 0.0
    assert unknown.finish()[1] < MIN_EXPLAINED
    clean = _two_cells(rng, slope=0.3, pixel_sigma=0.0).finish()
    assert clean[1] == pytest.approx(1.0)
