"""The frames' noise read off their sum, carried into T's entries and used by the fine fit's test (issue 21)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ilt.io.exr import read_exr, write_exr
from ilt.isf.build import build_isf, sample_like
from ilt.isf.directory import load_isf
from ilt.isf.fine import MIN_EXPLAINED, CellGeometry, FineAccumulator, fit_operator
from ilt.isf.noise import NOISE_FILE, T_VAR_FILE, TRIM_CONSISTENCY, fit_frame_noise, read_noise
from ilt.transport.regularise import BIAS_WEIGHT

READ_E = 3.0


def _smooth_field(shape=(160, 200)):
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    field = 800.0 * np.exp(-((x - 120) ** 2 + (y - 70) ** 2) / (2 * 45.0**2)) + 1.0 * x
    field[:40, :40] = 0.0          # a dark corner, as a scan's background: its noise reads below zero
    return field


def _noisy(image, gain, rng, read=READ_E):
    return (rng.poisson(np.maximum(image, 0) * gain) + rng.normal(0, read, image.shape)) / gain


def _frames(rng, count=12, shape=(120, 160)):
    """Smooth light (a broad bump and a ramp, a dark corner) and a sharp spot, moving."""
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    frames, spots = [], []
    for k in range(count):
        cx, cy = 20.0 + 10 * k, 30.0 + 5 * (k % 4)
        f = 400.0 * np.exp(-((x - 90) ** 2 + (y - 60) ** 2) / (2 * 40.0**2)) + 0.5 * x
        f[:30, :30] = 0.0
        frames.append(f + 5000.0 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 2.0))
        spots.append((cx, cy))
    return frames, np.array(spots)


@pytest.mark.parametrize("gain", [0.5, 5.0])
def test_the_frames_noise_is_read_off_the_frames(gain):
    """Frames with photon noise (gain e- per unit) and read noise (READ_E e-): the fitted
    variance is X / gain + (READ_E / gain)^2 within 15% from the dark corner to the
    bright light, and within 25% at 5x the brightest light it was fitted on; noise-free
    frames give no model."""
    rng = np.random.default_rng(1)
    clean, spots = _frames(rng)
    fit = fit_frame_noise([_noisy(f, gain, rng) for f in clean], spots)
    for level in (0.0, 100.0, 200.0, 350.0):     # the levels the frames hold many pixels at
        assert fit.pixel_variance(np.array([level]))[0] == pytest.approx(level / gain + (READ_E / gain) ** 2,
                                                                         rel=0.15)
    # above the frames' light (a spot's flank): the photon noise's line goes on
    assert fit.pixel_variance(np.array([3000.0]))[0] == pytest.approx(3000.0 / gain + (READ_E / gain) ** 2,
                                                                      rel=0.25)
    assert fit_frame_noise(clean, spots) is None


@pytest.mark.parametrize("gain", [0.5, 5.0])
def test_noise_that_never_goes_below_zero_is_read_too(gain):
    """Photon noise alone (no read noise: counts, or a path tracer's Monte Carlo) never
    reads below zero, yet it is noise: the fit gives X / gain within 20% where the frames
    hold light (its bins' trimmed mean squares: 13% low, the normal consistency factor's
    share) and 0 in the dark corner, which holds none, where it once gave no model and a
    Lambertian scan was refused for want of a noise floor. Noise-free frames still give
    none, their fine detail too (a texture as fine as noise, 1% of the light)."""
    rng = np.random.default_rng(3)
    clean, spots = _frames(rng)
    noisy = [_noisy(f, gain, rng, read=0.0) for f in clean]
    assert min(float(f.min()) for f in noisy) >= 0.0
    fit = fit_frame_noise(noisy, spots)
    for level in (100.0, 200.0, 350.0):
        assert fit.pixel_variance(np.array([level]))[0] == pytest.approx(level / gain, rel=0.2)
        assert fit.pixel_variance(np.array([level]))[0] / TRIM_CONSISTENCY == pytest.approx(level / gain, rel=0.08)
    assert fit.pixel_variance(np.array([0.0]))[0] == pytest.approx(0.0, abs=0.05 / gain)
    textured = [f * (1.0 + 0.01 * rng.standard_normal(f.shape)) for f in clean]
    assert fit_frame_noise(textured, spots) is None


def test_noise_that_is_a_share_of_the_light_is_told_from_photon_noise():
    """A path tracer's Monte Carlo noise (each pixel times Gamma(16, 1/16): a variance of
    1/16 of its level squared at every level) is read as a share of the light, within 6%
    (13% low before the trimmed mean squares' consistency factor); photon noise, with or
    without read noise, is not (0: its cells' variance as before)."""
    from ilt.isf.noise import light_share_variance

    rng = np.random.default_rng(4)
    clean, spots = _frames(rng)
    share = light_share_variance(fit_frame_noise([f * rng.gamma(16.0, 1.0 / 16.0, f.shape) for f in clean], spots))
    assert share == pytest.approx(1.0 / 16.0, rel=0.06)
    for read in (READ_E, 0.0):
        assert light_share_variance(fit_frame_noise([_noisy(f, 0.5, rng, read) for f in clean], spots)) == 0.0


def test_a_brackets_steps_are_followed():
    """A merged bracket's bright pixels come from a shorter exposure: their variance per
    unit of light is 8x the dim ones' above X = 150. The curve follows both (a line
    through them would be 3x off at one end or the other)."""
    rng = np.random.default_rng(2)
    clean, spots = _frames(rng)

    def sd(f):
        return np.sqrt(np.where(f < 150, 1.0 + 0.05 * f, 1.0 + 0.05 * 150 + 0.4 * (f - 150)))

    fit = fit_frame_noise([f + rng.normal(0, 1, f.shape) * sd(np.maximum(f, 0)) for f in clean], spots)
    for level in (10.0, 100.0, 300.0, 400.0):
        assert fit.pixel_variance(np.array([level]))[0] == pytest.approx(float(sd(np.array(level))) ** 2, rel=0.2)


def test_build_isf_carries_the_noise_into_t_and_decompose_uses_it(tmp_path):
    """noise.json's entry_sigma is the RMS of the noise in T's unit-column entries: built
    on the same cells from noisy and noise-free frames, T differs by about that much;
    decompose takes it as T's noise, and says where it came from."""
    from tests.isf.test_build import run

    sim, noisy = tmp_path / "sim", tmp_path / "noisy"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 12, "-o", sim)
    frames = noisy_frames(sim / "hdr", noisy, np.random.default_rng(3))
    run("centroids", noisy, "-o", tmp_path / "spots", "--workers", 1)
    build_isf(noisy, tmp_path / "spots", tmp_path / "isf", workers=1)
    record = read_noise(tmp_path / "isf")
    a = load_isf(tmp_path / "isf")
    scales = np.load(tmp_path / "isf" / "scales.npy")
    # the noise-free frames over the same cells: T's columns without the noise
    assert a.m == len(frames)                       # no beam dropped: row j is frame j
    clean = sample_like(a, np.stack([read_exr(f)[0][..., 0] for f in frames])).T
    difference = (a.T * scales - clean) / scales
    off = ~np.eye(a.m, dtype=bool)
    variance = np.load(tmp_path / "isf" / T_VAR_FILE)
    assert record["entry_sigma"] == pytest.approx(float(np.sqrt(np.mean(difference[off] ** 2))), rel=0.2)
    assert record["entry_sigma"] == pytest.approx(float(np.sqrt(np.mean(variance[off]))), rel=1e-5)
    # and entry by entry: the noisiest tenth of the entries as T_var says is as noisy as it says
    top = off & (variance >= np.quantile(variance[off], 0.9))
    assert float(np.mean(difference[top] ** 2)) == pytest.approx(float(np.mean(variance[top])), rel=0.3)
    outputs = json.loads((tmp_path / "isf" / "manifest.json").read_text())["outputs"]
    assert outputs.get(NOISE_FILE) and outputs.get(T_VAR_FILE)

    run("decompose", "--isf", tmp_path / "isf", sim / "photos" / "room.exr", "-o", tmp_path / "dec", "--no-cache")
    summary = json.loads((tmp_path / "dec" / "room" / "summary.json").read_text())
    operator = summary["operators"]
    assert operator["noise"] == pytest.approx(record["entry_sigma"])
    assert NOISE_FILE in operator["noise_source"]
    # and with the noise measured, T is denoised by default, along the cells' neighbours
    assert operator["regularisation_width"] > 0 and "along the cells' neighbours" in operator["regularisation"]
    # at the width of least estimated risk among those within the noise, each width's figures recorded
    risks = operator["regularisation_risks"]
    allowed = [row for row in risks if not row["past_the_noise"]]
    assert operator["regularisation_width"] == min(allowed, key=lambda row: row["risk"])["width"]
    assert all(row["risk"] == pytest.approx(BIAS_WEIGHT * row["bias2"] + row["variance"]) for row in risks)
    run("decompose", "--isf", tmp_path / "isf", sim / "photos" / "room.exr", "-o", tmp_path / "plain", "--no-cache",
        "--no-regularise")
    plain = json.loads((tmp_path / "plain" / "room" / "summary.json").read_text())["operators"]
    assert plain["noise"] == pytest.approx(record["entry_sigma"]) and plain["regularisation_width"] == 0


def noisy_frames(hdr, out, rng, electrons=2e4):
    """``hdr``'s beam frames with photon and read noise (``electrons`` at the brightest
    pixel of the scan) written to ``out`` as ilt's frames; the clean frames' paths."""
    frames = sorted(Path(hdr).glob("beam-*.exr"))
    gain = electrons / max(float(read_exr(f)[0].max()) for f in frames)
    shutil.copytree(hdr, out)
    for f in frames:
        image, attributes = read_exr(f)
        write_exr(out / f.name, _noisy(image.astype(np.float64), gain, rng).astype(np.float32), ["Y"],
                  {k: v for k, v in attributes.items() if k.startswith("ilt:")})
    return frames


def _two_cells(rng, slope, pixel_sigma):
    """Cells 0 and 1, the left and right halves of a 24 x 48 px frame, each a beam's own:
    beam 0 puts into cell 1 a field ``slope`` x (x - its centre) + 5, beam 1 a constant
    into cell 0, both with per-pixel noise ``pixel_sigma``. Returns the accumulator."""
    labels = np.zeros((24, 48), np.int64)
    labels[:, 24:] = 1
    geometry = CellGeometry.from_labels(labels, 2)
    fit = fit_operator(geometry, 1)
    acc = FineAccumulator(np.zeros((2, 2, 2), np.float32), geometry, 1, noise_aware=pixel_sigma > 0)
    x = np.arange(48.0)[None, :].repeat(24, axis=0)
    frames = np.stack([np.where(labels == 1, 5.0 + slope * (x - 35.5), 50.0), np.full(labels.shape, 5.0)])
    frames = frames + rng.normal(0, pixel_sigma, frames.shape)
    flat = [f.ravel() for f in frames]
    coefficients = np.stack([fit @ f for f in flat], axis=-1).reshape(2, 2, 2)
    raw = np.stack([np.bincount(labels.ravel(), f, 2) for f in flat], axis=1)
    squares = np.stack([np.bincount(labels.ravel(), f**2, 2) for f in flat], axis=1)
    variance = np.full((2, 2), pixel_sigma**2 * 24 * 24)      # the cell sums of each pixel's variance
    acc.add(0, coefficients, raw, squares, np.ones(2), variance if pixel_sigma else None)
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
    unknown.noise_aware = False
    unknown.noise_explained[:] = unknown.noise_total[:] = 0.0
    assert unknown.finish()[1] < MIN_EXPLAINED
    clean = _two_cells(rng, slope=0.3, pixel_sigma=0.0).finish()
    assert clean[1] == pytest.approx(1.0)


def test_a_cell_at_a_fold_keeps_no_plane_of_its_own():
    """The noise-free planar cell (share 1, its slope kept) given as ``keep_flat``: its
    coefficients are zeroed and its share is under MIN_EXPLAINED; the other cell as it was."""
    rng = np.random.default_rng(4)
    free = _two_cells(rng, slope=0.3, pixel_sigma=0.0)
    assert free.finish()[1] == pytest.approx(1.0) and np.any(free.out[:, 1, :] != 0)
    kept = _two_cells(np.random.default_rng(4), slope=0.3, pixel_sigma=0.0)
    kept.keep_flat = np.array([1])
    share = kept.finish()
    assert share[1] < MIN_EXPLAINED and np.all(kept.out[:, 1, :] == 0)
    np.testing.assert_array_equal(kept.out[:, 0, :], free.out[:, 0, :])


def test_a_cell_whose_light_varies_within_its_noise_is_kept_flat():
    """A slope whose light varies across the cell by about the spread of the noise's own
    variation (slope 0.05 under noise 1: 37-121 against a spread of 34): the share divides
    two noisy differences, and over six draws of the noise it read >= 0.9 in three (0.97,
    1.26, 1.56), sloping the cell on noise; each is flat now. A slope 6x steeper, whose
    light varies 70x its noise's spread, keeps its slope in all six."""
    for seed in range(6):
        faint = _two_cells(np.random.default_rng(seed), slope=0.05, pixel_sigma=1.0).finish()
        assert faint[1] < MIN_EXPLAINED
        steep = _two_cells(np.random.default_rng(seed), slope=0.3, pixel_sigma=1.0).finish()
        assert steep[1] >= MIN_EXPLAINED


def test_each_spots_own_cell_takes_its_pixels_squares_when_the_noise_is_a_share():
    """build-isf's T_var: columns 1-2 of m = 3 (a block from column 1): their own rows
    (1 and 2, T's diagonal) are at least share x their cells' sums of squared pixels (the
    block's last m rows) over 1 + share (a noisy square's mean excess); the other entries
    and a share of 0 leave the variance as it was."""
    from ilt.isf.build import _spot_cells_variance

    variance = np.full((3, 2), 0.5)
    block = np.vstack([np.ones((3, 2)), np.arange(6.0).reshape(3, 2) * 10])   # raw rows, then squares
    out = _spot_cells_variance(variance, block, 3, 1, 0.1)
    assert out[1, 0] == pytest.approx(0.1 * 20.0 / 1.1) and out[2, 1] == pytest.approx(0.1 * 50.0 / 1.1)
    assert out[0, 0] == out[0, 1] == out[1, 1] == out[2, 0] == 0.5
    assert _spot_cells_variance(variance, block, 3, 1, 0.0) is variance


def _chain(m: int = 200, sigma: float = 0.0, seed: int = 0):
    """A line of m cells, each beam's indirect light a smooth kernel of the distance (its
    q, indirect over own, changes slowly along the line), the diagonal ``sigma`` noisy;
    the neighbour pairs of the line."""
    i = np.arange(m)
    T = 0.02 * np.exp(-np.abs(i[:, None] - i[None, :]) / 15.0) * (1.0 + 0.3 * np.sin(i / 30.0))[:, None]
    T[np.diag_indices(m)] = 1.0 + sigma * np.random.default_rng(seed).standard_normal(m)
    return T, np.column_stack([i[:-1], i[1:]])


def test_the_diagonals_scatter_is_its_noise_and_caps_a_share_it_does_not_have():
    """diagonal_scatter reads the diagonal's relative noise off T (each beam's indirect over
    own light against its neighbours'): 10% noise reads 10% (within 20%), a noise-free
    diagonal under 0.5% (the chain's own curvature). cap_spot_cells leaves T_var's diagonal
    when the share said 10% and T scatters by 10%, and scales it down to the scatter (taken
    2 standard errors high) when T's diagonal is noise-free (a path tracer's spot sampled at
    every hit); T_var's other entries untouched; nothing to measure without neighbours."""
    from ilt.isf.noise import MEDIAN_VARIANCE_SE, cap_spot_cells, diagonal_scatter

    noisy, pairs = _chain(sigma=0.1)
    sigma, beams = diagonal_scatter(noisy, pairs)
    assert beams == 198 and sigma == pytest.approx(0.1, rel=0.2)
    clean, _ = _chain()
    assert diagonal_scatter(clean, pairs)[0] < 0.005
    for T, kept in ((noisy, True), (clean, False)):
        variance = np.full(T.shape, 1e-6)
        variance[np.diag_indices(200)] = (0.1 * np.diag(T)) ** 2
        before = variance.copy()
        record = cap_spot_cells(variance, T, pairs)
        assert record["predicted_sigma"] == pytest.approx(0.1)
        off = ~np.eye(200, dtype=bool)
        np.testing.assert_array_equal(variance[off], before[off])
        if kept:
            assert record["scaled_by"] > 0.6
        else:
            scatter = diagonal_scatter(T, pairs)[0]
            expected = scatter**2 * (1 + 2 * MEDIAN_VARIANCE_SE / np.sqrt(198)) / 0.01
            assert record["scaled_by"] == pytest.approx(expected) and record["scaled_by"] < 0.01
            np.testing.assert_allclose(np.diag(variance), np.diag(before) * expected)
    assert cap_spot_cells(np.zeros((200, 200)), clean, np.empty((0, 2), int)) is None


def test_spots_rendered_without_noise_are_not_taken_as_noisy_as_the_light_about_them(tmp_path):
    """A path tracer's noise of 16 samples in every pixel but the spots' (a spotlight
    sampled at every hit): the frames' noise is still read as a share of the light, which
    would make each spot's own cell as noisy as its pixels' squares say; build-isf sees T's
    diagonal scatter far less than that and scales T_var's diagonal down to it (noise.json's
    spot_cells: 9.7% said, 2% scattered, scaled by 0.08), and decompose's raise of the
    diagonal with it. With the spots noisy too it keeps them (scatter 13%: scaled by 1)."""
    from ilt.isf.noise import FrameNoise, light_share_variance
    from ilt.sim.render import render_scene
    from tests.isf.test_build import run

    sim = tmp_path / "sim"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 12, "-o", sim)
    p = json.loads((sim / "manifest.json").read_text())["parameters"]
    scene = render_scene("m", 32, p["albedo"], p["seed"], p["spot"], p["fine"], p["px_per_beam"])
    frames = sorted((sim / "hdr").glob("beam-*.exr"))
    records = {}
    for name, spots_noisy in (("direct", False), ("all", True)):
        rng = np.random.default_rng(5)
        out = tmp_path / name
        shutil.copytree(sim / "hdr", out)
        for j, f in enumerate(frames):
            image, attributes = read_exr(f)
            x = np.maximum(image[..., 0].astype(np.float64), 0.0)
            spot = np.zeros_like(x) if spots_noisy else np.minimum(scene.spot_image(j), x)
            noisy = spot + (x - spot) * rng.gamma(16.0, 1.0 / 16.0, x.shape)
            write_exr(out / f.name, noisy.astype(np.float32), ["Y"], {k: v for k, v in attributes.items()
                                                                      if k.startswith("ilt:")})
        run("centroids", out, "-o", tmp_path / f"spots-{name}", "--workers", 1)
        build_isf(out, tmp_path / f"spots-{name}", tmp_path / f"isf-{name}", workers=1)
        record = read_noise(tmp_path / f"isf-{name}")
        assert light_share_variance(FrameNoise.from_record(record)) > 0
        records[name] = record["spot_cells"]
    assert records["direct"]["predicted_sigma"] > 0.05 and records["direct"]["scaled_by"] < 0.15
    assert records["all"]["scaled_by"] > 0.5
    T = load_isf(tmp_path / "isf-direct").T
    variance = np.load(tmp_path / "isf-direct" / T_VAR_FILE)
    assert np.median(np.diag(variance) / np.diag(T) ** 2) < 0.15 * records["direct"]["predicted_sigma"] ** 2


@pytest.mark.parametrize("sigma", [0.05, 0.2])
def test_the_diagonals_scatter_on_a_grid_of_cells_with_an_edge(sigma):
    """On 300 Voronoi cells of a frame whose right half is 1.5x brighter (an edge the
    neighbours' mean crosses), each cell with 4-8 neighbours: a diagonal noisy by ``sigma``
    reads as sigma within 25% (the median leaves the edge's pairs out); noise-free, under 2%."""
    from ilt.isf.noise import diagonal_scatter
    from tests.transport.test_width_choice import _scene

    T, pairs = _scene()
    noisy = T.copy()
    noisy[np.diag_indices(len(T))] *= 1.0 + sigma * np.random.default_rng(2).standard_normal(len(T))
    measured, beams = diagonal_scatter(noisy, pairs)
    assert beams == len(T) and measured == pytest.approx(sigma, rel=0.25)
    assert diagonal_scatter(T, pairs)[0] < 0.02


def test_a_noise_record_says_whether_its_knots_are_trimmed_mean_squares():
    """noise.json keeps ``trimmed`` (frames with no negative pixel: trimmed mean squares,
    whose share of the light is divided by the normal consistency factor); a record written
    before it had the key reads as squared MADs, its share as it was."""
    from ilt.isf.noise import FrameNoise, light_share_variance

    levels = tuple(float(x) for x in np.linspace(1.0, 100.0, 12))
    noise = FrameNoise(levels, tuple(0.05 * x * x for x in levels), 8, 1000, 12, 0.0, trimmed=True)
    assert FrameNoise.from_record(noise.as_dict()) == noise
    old = {k: v for k, v in noise.as_dict().items() if k != "trimmed"}
    assert FrameNoise.from_record(old).trimmed is False
    assert light_share_variance(noise) == pytest.approx(0.05 / TRIM_CONSISTENCY)
    assert light_share_variance(FrameNoise.from_record(old)) == pytest.approx(0.05)
