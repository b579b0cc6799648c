"""centroids -> build-isf -> decompose end to end on rendered frames, against the truth."""

import json
import logging
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from ilt.cli import cli
from ilt.io.exr import read_exr, write_exr
from ilt.isf.build import build_isf, sample_like
from ilt.isf.cells import integrate, mosaic, voronoi_cells
from ilt.isf.directory import load_isf


def run(*args, ok=True):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output + repr(result.exception)
    return result


def _pipeline(root, beams):
    sim, spots = root / "sim", root / "spots"
    run("simulate", "m", "--frames", "--beams", beams, "--fine", 8, "--px-per-beam", 24, "-o", sim)
    run("centroids", sim / "hdr", "-o", spots, "--workers", 1)
    for sampling in ("cell", "point"):
        run("build-isf", sim / "hdr", spots, "-o", root / sampling, "--sampling", sampling, "--workers", 1)
        run("decompose", "--isf", root / sampling, sim / "photos" / "room.exr", sim / "photos" / "flashlight.exr",
            "-o", root / f"dec-{sampling}", "--no-cache", "--bounces", 4)
    return sim


def _errors(root, sim, sampling, kind):
    isf = load_isf(root / sampling)
    est = np.load(root / f"dec-{sampling}" / kind / "bounces.npy")
    truth = sample_like(isf, np.load(sim / "truth" / "photos" / f"{kind}-bounces.npy")[:4])
    return np.linalg.norm(est - truth, axis=1) / np.linalg.norm(truth, axis=1)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for beams in (16, 32):
        root = tmp_path_factory.mktemp(f"m{beams}")
        out[beams] = (root, _pipeline(root, beams))
    return out


def test_stage_directories(runs):
    root, sim = runs[32]
    spots = (root / "spots" / "spots.csv").read_text().splitlines()
    assert spots[0] == "beam,x,y,flux,peak,area,flags" and len(spots) == 33
    truth = np.loadtxt(sim / "truth" / "spots.csv", delimiter=",", skiprows=1)
    found = np.loadtxt(root / "spots" / "spots.csv", delimiter=",", skiprows=1, usecols=(1, 2))
    assert np.sqrt(((found - truth[:, 1:]) ** 2).sum(1).mean()) <= 0.02
    for name in ("T.npy", "samples.csv", "manifest.json", "cells.exr", "scales.npy", "T.png"):
        assert (root / "cell" / name).exists(), name
    assert (root / "spots" / "overlay.png").exists()
    isf = load_isf(root / "cell")
    np.testing.assert_allclose(np.linalg.norm(isf.T, axis=0), 1, rtol=1e-12)
    assert isf.cells.shape == isf.frame_shape and isf.cells.min() == -1 and isf.cells.max() == 31
    assert isf.layout == (1, 32) and isf.scales.shape == (32,)
    # the decomposition is shown as a mosaic of cells on the camera frame
    image, _ = read_exr(root / "dec-cell" / "room" / "samples" / "bounce-1.frame.exr")
    assert image.shape[:2] == isf.frame_shape


def test_cell_sampling_recovers_the_direct_image(runs):
    root, sim = runs[32]
    for kind in ("room", "flashlight"):
        cell, point = _errors(root, sim, "cell", kind), _errors(root, sim, "point", kind)
        assert cell[0] < 0.05, (kind, cell)
        assert point[0] > 0.3 and (point[1:] > 0.8).all()    # the paper's point sampling under-counts


def test_errors_fall_as_the_beam_density_grows(runs):
    for kind in ("room", "flashlight"):
        coarse = _errors(*runs[16], "cell", kind)
        fine = _errors(*runs[32], "cell", kind)
        assert (fine < coarse).all(), (kind, coarse, fine)


def test_cells_partition_the_lit_pixels():
    centroids = np.array([[2.0, 2.0], [7.0, 2.0], [4.5, 6.0]])
    lit = np.ones((9, 10), dtype=bool)
    lit[:, 0] = False
    labels = voronoi_cells(centroids, (9, 10), lit)
    assert (labels[:, 0] == -1).all() and set(np.unique(labels)) == {-1, 0, 1, 2}
    image = np.random.default_rng(0).random((9, 10))
    np.testing.assert_allclose(integrate(image, labels).sum(), image[lit].sum())
    painted = mosaic(integrate(np.ones((9, 10)), labels), labels)
    np.testing.assert_allclose(painted[lit], 1.0, rtol=1e-6)


def test_noise_free_frames_light_the_indirect_light_between_sparse_spots():
    """Noise-free frames: between a sparse scan's spots there is only indirect light, at
    2e-4 to 7.5e-4 of the spots' level on the simulator's M at 48 beams (benchmarks/
    noisy_sweep.py). The default --lit-fraction (the same in build_isf and the run
    config's table) lights all of it and none of the dark background; 1e-3 lit a quarter
    of that strip, and its bounces were then worse than on noisy frames (docs/fullres.md).
    A silhouette's pixels, partly background (under half the light of the lit pixels about
    them, next to one with none), are left out; a strip that ends on a pixel's edge keeps
    its last pixels."""
    import inspect

    from ilt.isf.build import build_isf, lit_mask
    from ilt.workspace.options import BUILD_ISF

    default = inspect.signature(build_isf).parameters["lit_fraction"].default
    assert BUILD_ISF["lit_fraction"].default == default
    frame_sum = np.zeros((40, 200))
    frame_sum[:, 20:180] = np.linspace(2e-4, 7.5e-4, 160)     # the indirect light, spots' level 1
    spots = np.array([[40.0, 20.0], [100.0, 20.0], [160.0, 20.0]])
    frame_sum[20, [40, 100, 160]] = 1.0
    lit, _ = lit_mask(frame_sum, spots, default)
    np.testing.assert_array_equal(lit, frame_sum > 0)
    frame_sum[:, 179] *= 0.3              # the object's edge cuts these pixels: 30% of them is lit
    frame_sum[:, 20] *= 0.8               # ... and 80% of these (both still above the fraction)
    assert frame_sum[:, [20, 179]].min() > default
    lit, _ = lit_mask(frame_sum, spots, default)
    np.testing.assert_array_equal(lit[:, 179], np.zeros(40, bool))
    np.testing.assert_array_equal(lit[:, 20:179], np.ones((40, 159), bool))
    assert not (lit_mask(frame_sum, spots, 1e-3)[0] & (frame_sum < 1.0)).any()


def test_a_silhouette_is_judged_on_the_indirect_light_not_the_spots():
    """An object's edge column of whole pixels (indirect light 1) next to the background,
    with two spots (peak 200, sigma 1 px) two pixels inside it: in the sum, the spots
    raise the median about some edge pixels past twice their light, and they read as
    partly background; judged on the sum without the spots (centroids' sum-indirect.exr)
    none does. The column the edge cuts (30% of each pixel) is left out either way."""
    from ilt.isf.build import _silhouette

    yy, xx = np.mgrid[0:24, 0:30].astype(np.float64)
    inside = (xx >= 5) & (xx < 25)
    indirect = np.where(inside, 1.0, 0.0)
    indirect[:, 24] *= 0.3
    direct = sum(200.0 * np.exp(-((xx - 7.0) ** 2 + (yy - y) ** 2) / 2) for y in (9.0, 15.0)) * inside
    total = indirect + direct
    assert _silhouette(total)[:, 5].sum() >= 3                      # whole pixels taken for an edge
    np.testing.assert_array_equal(_silhouette(total, indirect)[:, 5], np.zeros(24, bool))
    assert _silhouette(total)[:, 24].all() and _silhouette(total, indirect)[:, 24].all()


def test_the_lit_test_sees_faint_light_below_a_pixels_noise_and_stops_at_its_edge(monkeypatch):
    """A sum of noisy frames (sigma 8 a pixel): a bright square where the spots are, inside
    a plateau of faint light, 0.3 sigma a pixel (1.5 sigma of the 5 x 5 mean: the light
    between a sparse scan's spots), on a dark background. The 5 x 5 test alone lights
    little of the plateau's interior; the wide one-sided means (21 x 21: 6.3 sigma) light
    all of it, and nothing more than 5 px past the plateau's edge (a centred 21 x 21 mean
    would carry its light 10 px out) nor along the frame's edge (a 5 x 5 mean padded there
    lit 13 pixels of noise: it counts the edge pixels many times)."""
    import ilt.isf.build as build

    rng = np.random.default_rng(0)
    truth = np.zeros((120, 120))
    truth[20:100, 20:100] = 0.3 * 8.0
    truth[24:36, 24:36] = 100.0
    noisy = truth + rng.normal(0, 8.0, truth.shape)
    spots = np.array([[28.0, 28.0], [32.0, 32.0]])
    lit, _ = build.lit_mask(noisy, spots, 1e-3)
    near = np.zeros_like(lit)
    near[15:105, 15:105] = True
    assert lit[40:80, 40:80].all()
    assert not lit[~near].any()
    monkeypatch.setattr(build, "LIT_WIDE", ())
    narrow, _ = build.lit_mask(noisy, spots, 1e-3)
    assert narrow[40:80, 40:80].mean() < 0.5


def test_the_lit_test_leaves_out_what_only_noise_lights():
    """A frame sum of 64 noisy frames: a lit square of 100 units a pixel over a background of
    zero-mean noise (sigma 1 a frame, 8 for the sum). The 1e-3 fraction alone keeps half
    the background (its positive noise); the noise test keeps the square and, of the
    background past the mean's reach, only a rim of noise within 4 px (the 2-sigma
    hysteresis), and measures the 5 x 5 mean's noise (8 / 5). A faint band (4 sigma of the
    mean) touching the square is lit (a single 5-sigma cut lit a ninth of it). Noise-free, the
    same sum gives the fraction's mask."""
    from ilt.isf.build import LIT_SMOOTH, lit_mask

    rng = np.random.default_rng(0)
    truth = np.zeros((80, 80))
    truth[20:60, 20:60] = 100.0
    noisy = truth + rng.normal(0, 8.0, truth.shape)
    spots = np.array([[30.0, 30.0], [50.0, 50.0]])
    band = 4 * 8.0 / LIT_SMOOTH          # 4 sigma of the 5 x 5 mean: below the 5 of a lone pixel
    noisy[20:60, 60:66] += band          # a faint band touching the square
    lit, info = lit_mask(noisy, spots, 1e-3)
    background = truth == 0
    background[20:60, 60:66] = False
    far = np.ones_like(background)
    reach = LIT_SMOOTH + 2               # the mean's reach past the square and band, and its noise's rim
    far[20 - reach:60 + reach, 20 - reach:66 + reach] = False
    assert (noisy[background] > 1e-3 * 100).mean() > 0.4
    assert lit[22:58, 22:58].all() and not lit[far].any()
    # the band stays lit (0.90) where a single 5-sigma cut kept a ninth of it
    assert lit[22:58, 61:65].mean() > 0.85
    assert info["noise_sigma"] == pytest.approx(8.0 / LIT_SMOOTH, rel=0.1)
    clean, info = lit_mask(truth, spots, 1e-3)
    assert np.array_equal(clean, truth > 0.1) and info["noise_sigma"] == 0.0


def test_a_noisy_silhouette_leaves_out_the_background_and_the_pixels_its_edge_cuts(monkeypatch):
    """A sum of 64 noisy frames (sigma 8 a pixel): an object of 100 a pixel on a dark
    background, its right column cut by the edge (30% of each pixel) and its left one 80%.
    The lit test's 5 x 5 means let in the 2 px of background about the object (about 330
    pixels) and the cut column; peeled at the lit edge (ilt.isf.build._noisy_silhouette),
    where a pixel holds under half the light of the lit pixels inside it, most of them go
    (what stays is behind a speck of noise lit further out, whose own inside is dark), and
    no whole pixel of the object nor the 80% column does. Noise-free, the dark-pixel test
    alone (above) judges the silhouette."""
    from scipy.ndimage import distance_transform_cdt

    import ilt.isf.build as build

    truth = np.zeros((80, 80))
    truth[20:60, 20:60] = 100.0
    truth[20:60, 59] *= 0.3
    truth[20:60, 20] *= 0.8
    background = truth == 0
    near = background & (distance_transform_cdt(background, metric="chessboard") <= 2)
    spots = np.array([[30.0, 30.0], [50.0, 50.0]])
    for seed in range(2):
        noisy = truth + np.random.default_rng(seed).normal(0, 8.0, truth.shape)
        lit, info = build.lit_mask(noisy, spots, 1e-3, dark_noise=(1.0, 64))
        with monkeypatch.context() as patch:
            patch.setattr(build, "SILHOUETTE_PEELS", 0)
            unpeeled, _ = build.lit_mask(noisy, spots, 1e-3, dark_noise=(1.0, 64))
        assert unpeeled[20:60, 59].all() and (unpeeled & near).sum() >= 0.9 * near.sum()
        assert lit[20:60, 20:59].all()                       # the object's whole pixels and the 80% column
        assert lit[20:60, 59].mean() <= 0.3                  # the cut column (0.075-0.25 over six seeds)
        assert (lit & near).sum() <= 0.1 * near.sum()        # the background within the mean's reach (0.02-0.08)
        assert info["silhouette_pixels"] == np.count_nonzero(unpeeled & ~lit) and not (lit & ~unpeeled).any()
    assert build.lit_mask(truth, spots, 1e-3)[1]["silhouette_pixels"] == 0


def test_the_silhouettes_peel_leaves_no_island():
    """An object (100 a pixel) with the 2 px of background a noisy lit test lets in about it,
    one pixel of that outer ring reading 100 (noise). The peel keeps that pixel (half of the
    pixels inside it are the object's) while it takes the background inside it: left alone it
    would be an island of its own, which the fold cells count as a region. It goes too, and
    exactly the ring does."""
    from ilt.isf.build import _noisy_silhouette

    light = np.zeros((40, 40))
    light[10:30, 10:30] = 100.0
    lit = np.zeros((40, 40), bool)
    lit[8:32, 8:32] = True
    light[8, 20] = 100.0
    out = _noisy_silhouette(lit, light, 1.0)
    object_ = np.zeros_like(lit)
    object_[10:30, 10:30] = True
    np.testing.assert_array_equal(out, lit & ~object_)


def test_the_largest_frames_mean_lights_no_noise_at_the_frames_edges():
    """The peak test (peak.exr: the largest of the frames' 5 x 5 means, ilt.spots.stage) on
    200 frames of pure noise (sigma 1), judged with the noise of a 25-pixel mean: no pixel
    lit, at the edges either. With the windows padded (the edge pixels repeated, as before)
    a corner's mean held the noise of 5 pixels, not 25, and the largest of 200 lit specks
    at the frame's corners. inside_mean: an edge pixel takes the mean of the window next to
    it, exactly."""
    from scipy.ndimage import uniform_filter

    from ilt.isf.build import LIT_SIGMAS, _peak_test
    from ilt.spots.stage import PEAK_SMOOTH, inside_mean

    rng = np.random.default_rng(4)
    frames = rng.normal(0.0, 1.0, (200, 24, 40))
    mean = inside_mean(frames[0], PEAK_SMOOTH)
    assert mean[0, 0] == pytest.approx(frames[0, :5, :5].mean()) and mean[23, 39] == pytest.approx(frames[0, -5:, -5:].mean())
    assert mean[10, 20] == pytest.approx(frames[0, 8:13, 18:23].mean())
    spots = np.array([[20.0, 12.0]])
    noise = 1.0 / PEAK_SMOOTH
    inside = np.max([inside_mean(f, PEAK_SMOOTH) for f in frames], axis=0)
    assert not _peak_test(inside, spots[:, 1].astype(int), spots[:, 0].astype(int), 1e-4, LIT_SIGMAS, noise, 200).any()
    padded = np.max([uniform_filter(f, PEAK_SMOOTH, mode="nearest") for f in frames], axis=0)
    specks = _peak_test(padded, spots[:, 1].astype(int), spots[:, 0].astype(int), 1e-4, LIT_SIGMAS, noise, 200)
    assert specks.any() and not specks[3:-3, 3:-3].any()


def test_executor_is_pluggable_and_gives_the_same_T(runs, tmp_path):
    root, sim = runs[16]
    with ThreadPoolExecutor(2) as ex:
        build_isf(sim / "hdr", root / "spots", tmp_path / "isf", executor=ex, chunk=3)
    np.testing.assert_array_equal(np.load(tmp_path / "isf" / "T.npy"), np.load(root / "cell" / "T.npy"))


def _whole_array_reference(isf_dir, hdr_dir, degree):
    """T and the fine coefficients the way build-isf made them before it streamed them
    (issue 15): every column in memory, T = raw / scales on the whole, and the fine
    coefficients finished on whole (K, m, m) float64 arrays (the code of that build)."""
    from ilt.io.frames import open_hdr_directory
    from ilt.isf.build import _column_chunk
    from ilt.isf.fine import MIN_EXPLAINED, CellGeometry, basis_terms

    hdr = open_hdr_directory(hdr_dir)
    plan = json.loads((isf_dir / "manifest.json").read_text())["beams"]
    m, K = len(plan), basis_terms(degree)
    block = _column_chunk(plan, [hdr.files[b] for b in plan], hdr.frame_shape, str(isf_dir / "cells.exr"), m,
                          None, degree)
    raw, coefficients, squares = block[:m], block[m:-m].reshape(K, m, m), block[-m:]
    scales = np.linalg.norm(raw, axis=0)
    geometry = CellGeometry.from_labels(load_isf(isf_dir).cells, m)
    diagonal = np.arange(m)
    coefficients[:, diagonal, diagonal] = 0.0
    variation = squares - raw * raw / np.maximum(geometry.area, 1.0)[:, None]
    variation[diagonal, diagonal] = 0.0
    explained = np.einsum("aij,iab,bij->i", coefficients, geometry.gram(degree), coefficients)
    total = variation.sum(axis=1)
    share = np.where(total > 0, explained / np.where(total > 0, total, 1.0), 1.0)
    coefficients[:, share < MIN_EXPLAINED, :] = 0.0
    coefficients /= scales[None, None, :]
    return raw / scales, scales, coefficients.astype(np.float32), share


@pytest.mark.parametrize("degree, chunk", [(1, 16), (2, 5)])
def test_streamed_t_and_fine_coefficients_equal_the_whole_array_build(runs, tmp_path, degree, chunk):
    """T and scales bit for bit, the float32 coefficients to their rounding, the flat
    cells the same, whatever the column blocks (chunk 5: uneven blocks, the last short).
    (No fold cells: the reference is the Voronoi cells' and the 90% rule's.)"""
    root, sim = runs[32]
    with ThreadPoolExecutor(2) as ex:
        build_isf(sim / "hdr", root / "spots", tmp_path / "isf", executor=ex, chunk=chunk, fine_degree=degree,
                  fold_cells=False)
    T, scales, coefficients, share = _whole_array_reference(tmp_path / "isf", sim / "hdr", degree)
    np.testing.assert_array_equal(np.load(tmp_path / "isf" / "T.npy"), T)
    np.testing.assert_array_equal(np.load(tmp_path / "isf" / "scales.npy"), scales)
    stored = np.load(tmp_path / "isf" / "fine" / "coefficients.npy")
    assert stored.dtype == np.float32 and stored.shape == coefficients.shape
    np.testing.assert_allclose(stored, coefficients, rtol=2e-7, atol=0)
    fine = json.loads((tmp_path / "isf" / "fine" / "manifest.json").read_text())
    assert fine["flat_cells"] == int((share < 0.9).sum())
    assert "fine/coefficients.npy" in json.loads((tmp_path / "isf" / "manifest.json").read_text())["outputs"]
    # the ISF the other stages load: T as a plain array, the fine operator against it
    assert load_isf(tmp_path / "isf").T.shape == T.shape


def test_t_is_hashed_once_for_both_manifests(runs, tmp_path, monkeypatch):
    """build-isf reads T.npy once for its two fingerprints (the ISF manifest's file hash,
    the fine operator's array fingerprint) and fine/coefficients.npy once (the fine
    manifest's hash is the ISF manifest's too); each is what hashing the file afresh gives."""
    import ilt.io.manifest as manifest
    import ilt.isf.fine as fine_module

    root, sim = runs[16]
    hashed, real_file, real_array = [], manifest.fingerprint_file, manifest.fingerprint_array
    monkeypatch.setattr(manifest, "fingerprint_file", lambda path, *a: hashed.append(Path(path).name) or
                        real_file(path, *a))
    for module in (manifest, fine_module):
        monkeypatch.setattr(module, "fingerprint_array", lambda a: hashed.append(np.shape(a)) or real_array(a))
    build_isf(sim / "hdr", root / "spots", tmp_path / "isf")
    monkeypatch.undo()
    m = json.loads((tmp_path / "isf" / "manifest.json").read_text())
    T = np.load(tmp_path / "isf" / "T.npy")
    assert hashed.count("T.npy") == 0 and hashed.count(T.shape) == 0 and hashed.count("coefficients.npy") == 1
    assert m["outputs"]["T.npy"] == manifest.fingerprint_file(tmp_path / "isf" / "T.npy")
    assert m["outputs"]["fine/coefficients.npy"] == manifest.fingerprint_file(tmp_path / "isf" / "fine" /
                                                                              "coefficients.npy")
    fine = json.loads((tmp_path / "isf" / "fine" / "manifest.json").read_text())
    assert fine["inputs"]["T"] == manifest.fingerprint_array(T)


def test_fingerprint_npy_is_the_file_hash_and_the_array_fingerprint(tmp_path):
    from ilt.io.manifest import fingerprint_array, fingerprint_file, fingerprint_npy

    a = np.random.default_rng(0).normal(size=(37, 5))
    np.save(tmp_path / "a.npy", a)
    assert fingerprint_npy(tmp_path / "a.npy", chunk=64) == (fingerprint_file(tmp_path / "a.npy"),
                                                              fingerprint_array(a))
    np.save(tmp_path / "f.npy", np.asfortranarray(a))
    with pytest.raises(ValueError, match="f.npy: not a C-order"):
        fingerprint_npy(tmp_path / "f.npy")


def test_flagged_and_duplicate_beams_are_dropped_with_a_warning(runs, tmp_path, caplog):
    root, sim = runs[16]
    spots = tmp_path / "spots"
    shutil.copytree(root / "spots", spots)
    lines = (spots / "spots.csv").read_text().splitlines()
    fields = lines[4].split(",")
    lines[4] = ",".join(fields[:-1] + ["multiple=0.4"])                     # beam 3 flagged
    f7, f8 = lines[8].split(","), lines[9].split(",")
    lines[9] = ",".join([f8[0], str(float(f7[1]) + 0.5), f7[2]] + f8[3:])   # beam 8 on top of beam 7
    (spots / "spots.csv").write_text("\n".join(lines) + "\n")
    caplog.set_level(logging.INFO, logger="ilt.isf")
    summary = build_isf(sim / "hdr", spots, tmp_path / "isf", workers=1)
    assert [d["beam"] for d in summary["drops"]] == [3, 8]
    # the flag was centroids' to warn of (with what to look at); the duplicate is build-isf's own finding
    levels = {r.getMessage().split(":")[0]: r.levelname for r in caplog.records if "dropping beam" in r.getMessage()}
    assert levels == {"dropping beam 3": "INFO", "dropping beam 8": "WARNING"}
    assert "flagged: multiple=0.4" in summary["drops"][0]["reason"]
    assert "near-duplicate" in summary["drops"][1]["reason"]
    assert "dropping beam 3" in caplog.text and "dropping beam 8" in caplog.text
    isf = load_isf(tmp_path / "isf")
    assert isf.m == 14 and isf.layout == (1, 16) and list(isf.beams[:4]) == [0, 1, 2, 4]
    manifest = json.loads((tmp_path / "isf" / "manifest.json").read_text())
    assert manifest["drops"] == summary["drops"]
    # a photo still decomposes, shown on the plan's strip with gaps
    run("decompose", "--isf", tmp_path / "isf", sim / "photos" / "room.exr", "-o", tmp_path / "dec", "--no-cache")
    strip, _ = read_exr(tmp_path / "dec" / "room" / "samples" / "bounce-1.exr")
    assert strip.shape[:2] == (1, 16) and strip[0, 3, 0] == 0 and strip[0, 2, 0] > 0


def _copy_hdr(runs, tmp_path):
    hdr = tmp_path / "hdr"
    shutil.copytree(runs[16][1] / "hdr", hdr)
    return hdr


@pytest.mark.parametrize("case", ["truncated", "sizes", "missing", "empty", "spots-beam"])
def test_bad_input_fails_cleanly(runs, tmp_path, case):
    root, _ = runs[16]
    hdr = _copy_hdr(runs, tmp_path)
    out = tmp_path / "out"
    if case == "truncated":
        data = (hdr / "beam-00005.exr").read_bytes()
        (hdr / "beam-00005.exr").write_bytes(data[: len(data) // 2])
        result = run("centroids", hdr, "-o", out, "--workers", 1, ok=False)
        named = "beam-00005.exr"
    elif case == "sizes":
        write_exr(hdr / "beam-00007.exr", np.zeros((5, 5), np.float32))
        result = run("centroids", hdr, "-o", out, "--workers", 1, ok=False)
        named = "beam-00007.exr"
    elif case == "missing":
        (hdr / "beam-00009.exr").unlink()
        result = run("centroids", hdr, "-o", out, "--workers", 1, ok=False)
        named = "beam 9"
    elif case == "empty":
        empty = tmp_path / "empty"
        empty.mkdir()
        result = run("centroids", empty, "-o", out, ok=False)
        named = str(empty)
    else:
        spots = tmp_path / "spots"
        shutil.copytree(root / "spots", spots)
        with open(spots / "spots.csv", "a") as f:
            f.write("16,5.0,5.0,1.0,1.0,4,\n")
        result = run("build-isf", hdr, spots, "-o", out, "--workers", 1, ok=False)
        named = "beam 16"
    assert result.exit_code == 1
    message = result.output.strip().splitlines()[-1]
    assert message.startswith("ilt: error:") and named in message, result.output
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_pixel_mapping_from_headers_else_the_manifest_else_full_resolution(tmp_path):
    from ilt.io.exr import write_exr
    from ilt.io.frames import (
        FULL_RESOLUTION,
        FrameError,
        PixelMapping,
        open_hdr_directory,
    )
    from ilt.io.manifest import write_json

    half = PixelMapping((0.5, 0.5), 2.0)
    for name in ("plain", "manifest", "headers", "mixed"):
        (tmp_path / name).mkdir()
        for b in range(2):
            attrs = half.attributes() if name == "headers" or (name == "mixed" and b) else {}
            write_exr(tmp_path / name / f"beam-{b:05d}.exr", np.ones((4, 6)), attributes=attrs)
    write_json(tmp_path / "manifest" / "manifest.json", {"pixel_mapping": half.as_dict()})
    assert open_hdr_directory(tmp_path / "plain").mapping == FULL_RESOLUTION
    assert open_hdr_directory(tmp_path / "manifest").mapping == half
    assert open_hdr_directory(tmp_path / "headers").mapping == half
    with pytest.raises(FrameError, match="beam-00001.exr: pixel mapping"):
        open_hdr_directory(tmp_path / "mixed")
    np.testing.assert_allclose(half.to_full(half.to_grid([[16.0, 10.5]])), [[16.0, 10.5]])
    np.testing.assert_allclose(half.to_full([[3, 2]]), [[6.5, 4.5]])


def test_centroids_and_isf_decode_once_and_agree_with_the_two_stages(runs, tmp_path):
    """The combined run (every EXR decoded once, frames kept as scratch) writes the same
    spots and the same T, bit for bit, as `ilt centroids` then `ilt build-isf`, in a
    pool of 2 workers as in one, and removes its scratch frames."""
    from ilt.isf.build import centroids_and_isf

    root, sim = runs[16]
    for workers in (1, 2):
        out = tmp_path / f"j{workers}"
        centroids_and_isf(sim / "hdr", out / "spots", out / "isf", workers=workers)
        assert (out / "spots" / "spots.csv").read_text() == (root / "spots" / "spots.csv").read_text()
        for name in ("T.npy", "scales.npy"):
            assert np.array_equal(np.load(out / "isf" / name), np.load(root / "cell" / name)), (workers, name)
        assert sorted(p.name for p in out.iterdir()) == ["isf", "spots"]


@given(n=st.integers(0, 400), size=st.integers(1, 40))
@settings(max_examples=200, deadline=None)
def test_chunks_cover_every_beam_once_in_order_with_small_ones_last(n, size):
    from ilt.parallel.chunks import chunks

    parts = chunks(list(range(n)), size)
    assert [b for part in parts for b in part] == list(range(n))
    lengths = [len(p) for p in parts]
    assert all(0 < k <= size for k in lengths)
    small = max(1, size // 4)
    assert sum(k < size for k in lengths) <= -(-min(n, 3 * size) // small)  # only the tail is split
    assert lengths == sorted(lengths, reverse=True)


def test_centroids_and_isf_when_the_disk_fills_while_keeping_frames(runs, tmp_path, monkeypatch, caplog):
    """Frames that cannot be kept (disk full, after part of a frame was written) are left
    out of the scratch's record and decoded again by build-isf: the same T, a line
    naming the file and beam, and no EXR frame ever removed."""
    import errno

    import ilt.io.frames
    from ilt.isf.build import centroids_and_isf

    root, sim = runs[16]
    frames = sorted(p.name for p in (sim / "hdr").iterdir())
    real_keep = ilt.io.frames.FrameScratch.keep
    recorded = []

    def keep(self, fd, beam, frame):  # beams 10 and after fail half-way
        if beam >= 10:
            os.pwrite(fd, b"\xff" * (frame.nbytes // 2), beam * self.frame_bytes)
            raise OSError(errno.ENOSPC, "No space left on device")
        real_keep(self, fd, beam, frame)

    real_kept = ilt.io.frames.FrameScratch.kept

    def kept(self):
        recorded.append(real_kept(self))
        return recorded[-1]

    monkeypatch.setattr(ilt.io.frames.FrameScratch, "keep", keep)
    monkeypatch.setattr(ilt.io.frames.FrameScratch, "kept", kept)
    with caplog.at_level(logging.INFO, logger="ilt.spots"):
        centroids_and_isf(sim / "hdr", tmp_path / "spots", tmp_path / "isf", workers=1)
    assert any("No space left on device" in r.message and "beam 10" in r.message
               and "build-isf will decode it again" in r.message for r in caplog.records)
    assert recorded == [frozenset(range(10))]
    for name in ("T.npy", "scales.npy"):
        assert np.array_equal(np.load(tmp_path / "isf" / name), np.load(root / "cell" / name)), name
    assert sorted(p.name for p in (sim / "hdr").iterdir()) == frames
    assert sorted(p.name for p in tmp_path.iterdir()) == ["isf", "spots"]


def test_frame_scratch_keeps_frames_bit_for_bit_and_trusts_only_its_record(tmp_path):
    """Frames written in any order read back identical; only recorded beams of the
    recorded frame size count as kept; a frame of another size is refused."""
    from ilt.io.frames import FrameError, FrameScratch

    rng = np.random.default_rng(4)
    frames = {b: rng.normal(size=(5, 7)).astype(np.float32) for b in (3, 0, 6)}
    scratch = FrameScratch(tmp_path, (5, 7))
    assert scratch.kept() == frozenset()  # nothing recorded yet
    fd = scratch.open(write=True)
    try:
        for b, f in frames.items():
            scratch.keep(fd, b, f)
        with pytest.raises(FrameError, match="beam 2: frame of 7 x 6 pixels"):
            scratch.keep(fd, 2, np.zeros((6, 7), np.float32))
    finally:
        os.close(fd)
    scratch.record([6, 0, 3])
    assert scratch.kept() == frozenset({0, 3, 6})
    assert FrameScratch(tmp_path, (7, 5)).kept() == frozenset()  # another size: not these frames
    fd = scratch.open()
    try:
        out = np.empty((5, 7), np.float32)
        for b, f in frames.items():
            assert np.array_equal(scratch.read(fd, b, out), f)
        with pytest.raises(FrameError, match="beam 9"):
            scratch.read(fd, 9, out)  # past the end of the file
    finally:
        os.close(fd)


def test_a_denser_scan_covers_at_least_what_a_sparser_one_did(tmp_path):
    """Issue 21: cells end where the scan's light ends, not 2 spot spacings out. On a
    strip 32 rows tall at 6 px between spots, 2 spacings of the 32-beam scan (12 px) left
    a third of the rows outside every cell while the 16-beam scan (every other spot of the
    same frames and sum) covered them: the denser scan covered less."""
    sim, spots, sparse = tmp_path / "sim", tmp_path / "spots", tmp_path / "sparse"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 6, "--spot", 0.1, "-o", sim)
    run("centroids", sim / "hdr", "-o", spots, "--workers", 1)
    shutil.copytree(spots, sparse)
    rows = (spots / "spots.csv").read_text().splitlines()
    (sparse / "spots.csv").write_text("\n".join(rows[:1] + rows[1::2]) + "\n")
    covered = {}
    for name, where in (("dense", spots), ("sparse", sparse)):
        build_isf(sim / "hdr", where, tmp_path / f"isf-{name}", workers=1, fine_degree=None)
        covered[name] = load_isf(tmp_path / f"isf-{name}").cells >= 0
    lit = read_exr(spots / "sum.exr")[0][..., 0] > 0
    assert (covered["dense"] >= covered["sparse"]).all()
    assert covered["dense"][lit].mean() > 0.95
    # and a radius, when asked for, still bounds them
    build_isf(sim / "hdr", spots, tmp_path / "isf-r", workers=1, fine_degree=None, max_cell_radius=3.0)
    assert (load_isf(tmp_path / "isf-r").cells >= 0).mean() < 0.5 * covered["dense"].mean()


def test_a_matte_scene_is_judged_lambertian_from_its_cells_and_points(runs):
    """The rendered M is Lambertian: reciprocity holds to the cells' variation (build-isf's lambertian.json)."""
    root, _ = runs[32]
    for sampling in ("cell", "point"):
        verdict = json.loads((root / sampling / "lambertian.json").read_text())
        assert verdict["verdict"] == "lambertian", verdict
        assert verdict["reciprocity_residual"] < 0.5 * verdict["tolerance"], verdict
        assert verdict["pairs"] >= 100 and verdict["beams"] == 32
        assert (root / sampling / "lambertian.png").exists()
        assert json.loads((root / sampling / "manifest.json").read_text())["lambertian"]["verdict"] == "lambertian"


def test_a_rebuild_keeps_what_an_earlier_build_covered(runs, tmp_path):
    """``--keep-covered``: a pixel an earlier build's cells covered stays covered, in the cell
    of its nearest spot, whatever this build's lit test says; the earlier cells are an input
    of the manifest. (The lit test is cut here by a 50x higher --lit-fraction, which leaves out
    the faint rim as noise does a denser scan's: docs/fullres.md.)"""
    root, sim = runs[32]
    rows = (root / "spots" / "spots.csv").read_text().splitlines()
    sparse = tmp_path / "sparse-spots"
    shutil.copytree(root / "spots", sparse)
    (sparse / "spots.csv").write_text("\n".join(rows[:1] + rows[1::2]) + "\n")
    build_isf(sim / "hdr", sparse, tmp_path / "sparse", workers=1, fine_degree=None)
    earlier = load_isf(tmp_path / "sparse").cells >= 0
    run("build-isf", sim / "hdr", root / "spots", "-o", tmp_path / "cut", "--lit-fraction", 0.05, "--workers", 1,
        "--no-fine")
    cut = load_isf(tmp_path / "cut").cells
    assert (earlier & (cut < 0)).sum() > 100        # the cut lit test loses part of the earlier coverage
    run("build-isf", sim / "hdr", root / "spots", "-o", tmp_path / "kept", "--lit-fraction", 0.05, "--workers", 1,
        "--no-fine", "--keep-covered", tmp_path / "sparse", "--no-fold-cells")
    isf = load_isf(tmp_path / "kept")
    assert ((isf.cells >= 0) == (earlier | (cut >= 0))).all()
    # each pixel in the cell of its nearest spot: the Voronoi labels of the union (no fold cells, which
    # noise-free frames now get too: tests/isf/test_folds.py)
    expected = voronoi_cells(isf.mapping.to_grid(isf.samples), isf.cells.shape, earlier | (cut >= 0))
    assert (isf.cells == expected).all()
    manifest = json.loads((tmp_path / "kept" / "manifest.json").read_text())
    cells = str(tmp_path / "sparse" / "cells.exr")
    assert manifest["parameters"]["keep_covered"] == cells and cells in manifest["inputs"]
    assert manifest["coverage"]["lit"]["kept_from"]["added"] == int((earlier & (cut < 0)).sum())


@pytest.mark.parametrize("case", ["itself", "other-frame", "point", "missing", "not-cells"])
def test_keeping_coverage_from_the_wrong_build_is_one_line(runs, tmp_path, case):
    """--keep-covered naming the build it replaces, a build of another frame size, with point
    sampling, a directory without cells, or an image that is not an ISF's cells: one line
    naming it, nothing written."""
    root, sim = runs[32]
    out, extra, named = tmp_path / "out", [], None
    if case == "itself":
        shutil.copytree(root / "cell", out)
        before = (out / "T.npy").read_bytes()
        keep, extra, named = out, ["--force"], str(out)
    elif case == "other-frame":
        keep, named = runs[16][0] / "cell", str(runs[16][0] / "cell" / "cells.exr")
    elif case == "point":
        keep, extra, named = root / "cell", ["--sampling", "point"], "point sampling"
    elif case == "missing":
        keep, named = root / "spots", str(root / "spots" / "cells.exr")
    else:   # a decompose's coverage.exr (0 and 1, no -1) is not an ISF's cells
        keep = named = str(root / "dec-cell" / "room" / "coverage.exr")
    result = run("build-isf", sim / "hdr", root / "spots", "-o", out, "--workers", 1, "--keep-covered", keep,
                 *extra, ok=False)
    assert result.exit_code == 1
    message = result.output.strip().splitlines()[-1]
    assert message.startswith("ilt: error:") and named in message, result.output
    if case == "itself":
        assert (out / "T.npy").read_bytes() == before
    else:
        assert not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())
