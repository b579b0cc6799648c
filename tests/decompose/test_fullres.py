"""Full-resolution bounce images (ilt.isf.fine) against the simulator's per-pixel truth."""

import json
import shutil

import numpy as np
import OpenImageIO as oiio
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exr import read_exr, write_exr
from ilt.isf.cells import integrate
from ilt.isf.directory import load_isf
from ilt.isf.fine import CellGeometry, basis_terms, fit_operator

KINDS = ("flashlight", "room", "projector")


def run(*args, ok=True):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output + repr(result.exception)
    return result


def _scan(root, beams, px_per_beam=16, scene="m"):
    """Rendered scene -> spots -> ISF with its fine operator -> every photo decomposed."""
    sim, spots, isf, dec = root / "sim", root / "spots", root / "isf", root / "dec"
    run("simulate", scene, "--frames", "--beams", beams, "--fine", 8, "--px-per-beam", px_per_beam, "-o", sim)
    run("centroids", sim / "hdr", "-o", spots, "--workers", 1)
    run("build-isf", sim / "hdr", spots, "-o", isf, "--workers", 1)
    run("decompose", "--isf", isf, *[sim / "photos" / f"{k}.exr" for k in KINDS], "-o", dec, "--no-cache")
    return sim, isf, dec


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    return {beams: _scan(tmp_path_factory.mktemp(f"full{beams}"), beams) for beams in (16, 48)}


def _image(path):
    return read_exr(path)[0][:, :, 0].astype(np.float64)


def _errors(sim, dec, kind, bounces=3):
    """Relative L2 error per bounce over the covered pixels, and of the indirect image."""
    truth = np.load(sim / "truth" / "photos" / f"{kind}-bounces.npy").astype(np.float64)
    covered = _image(dec / kind / "coverage.exr") > 0
    rel = [np.linalg.norm((_image(dec / kind / f"bounce-{n}.exr") - truth[n - 1])[covered])
           / np.linalg.norm(truth[n - 1][covered]) for n in range(1, bounces + 1)]
    indirect = truth[1:].sum(axis=0)
    rel.append(np.linalg.norm((_image(dec / kind / "indirect.exr") - indirect)[covered])
               / np.linalg.norm(indirect[covered]))
    return np.array(rel)


def test_outputs_are_at_the_photos_resolution(scans):
    sim, isf, dec = scans[48]
    photo = read_exr(sim / "photos" / "room.exr")[0]
    names = [f"bounce-{n}" for n in range(1, 9)] + ["indirect", "residual", "coverage"]
    for name in names:
        image, attrs = read_exr(dec / "room" / f"{name}.exr")
        assert image.shape == photo.shape and image.dtype == np.float32, name
        assert attrs["ilt:quantity"] == name
    assert (dec / "room" / "samples" / "bounce-1.exr").exists()
    assert np.load(dec / "room" / "bounces.npy").shape == (8, 48)
    summary = json.loads((dec / "room" / "summary.json").read_text())["full_resolution"]
    assert summary["written"] and 0.9 < summary["coverage"] <= 1
    coverage = _image(dec / "room" / "coverage.exr")
    assert summary["coverage"] == pytest.approx(np.mean(coverage == 1))
    assert summary["rim"] == pytest.approx(np.mean(coverage == 0.5))


def test_pixels_close_and_cells_integrate_to_the_sample_bounces(scans):
    """photo = bounce 1 + ... + bounce N + residual at every pixel; bounce 1 is never
    negative (no pixel holds more indirect light than the photo: PhotoBound); and each
    full-resolution image integrates over every cell to its sample-level vector (the
    cell-consistency identity: the basis has zero sum over each cell, the constant is T's
    own, the light a bounded pixel gives up goes to its cell's others), except in the cells
    whose sample-level bounce 1 is negative, where no pixel's can be."""
    sim, isf_dir, dec = scans[48]
    isf = load_isf(isf_dir)
    negative, counts = 0, {}
    for kind in KINDS:
        out = dec / kind
        photo = _image(sim / "photos" / f"{kind}.exr")
        images = np.stack([_image(out / f"bounce-{n}.exr") for n in range(1, 9)])
        residual = _image(out / "residual.exr")
        scale = np.abs(photo).max()
        assert photo.min() >= 0 and images[0].min() >= -1e-6 * scale
        assert np.abs(images.sum(axis=0) + residual - photo).max() < 1e-6 * scale
        bounces = np.load(out / "bounces.npy")
        atol = 1e-6 * np.abs(bounces[0]).max()
        kept = bounces[0] >= 0
        negative += int(np.count_nonzero(~kept))
        for n in range(8):
            np.testing.assert_allclose(integrate(images[n], isf.cells, isf.m)[kept], bounces[n][kept], atol=atol)
        np.testing.assert_allclose(integrate(residual, isf.cells, isf.m)[kept], np.load(out / "residual.npy")[kept],
                                   atol=atol)
        np.testing.assert_allclose(photo - images[0], _image(out / "indirect.exr"), atol=1e-6 * scale)
        # a bounded pixel's indirect light is its photo's, so its bounce 1 is 0: summary.json counts them
        bounded = json.loads((out / "summary.json").read_text())["full_resolution"]["bounded_pixels"]
        # (and pixels below it that their cell's give-back filled to it)
        inside = _image(out / "coverage.exr") == 1
        zero = inside & (np.abs(images[0]) <= 1e-6 * photo) & (photo > 0)
        assert bounded <= np.count_nonzero(zero), (kind, bounded, np.count_nonzero(zero))
        counts[kind] = bounded
    assert negative > 0     # the flashlight's shadow: cells the bound changes are in this test
    assert counts["flashlight"] > 0


def test_errors_against_the_per_pixel_truth_fall_as_m_grows(scans):
    """Noise-free M scene: per-pixel bounce errors (measured: at m = 48 the direct image
    1.4-2.6%, bounce 2 2.8-5.4%, bounce 3 3.4-9.3%; every one lower than at m = 16)."""
    coarse, fine = ({k: _errors(scans[b][0], scans[b][2], k) for k in KINDS} for b in (16, 48))
    for kind in KINDS:
        assert fine[kind][0] < 0.035, (kind, fine[kind])
        assert fine[kind][1] < 0.08, (kind, fine[kind])
        assert fine[kind][2] < 0.12, (kind, fine[kind])
        assert np.all(fine[kind] < coarse[kind]), (kind, coarse[kind], fine[kind])


def test_textured_albedo(tmp_path):
    """Texture finer than a cell is direct light to the model (the photo's detail goes to
    bounce 1): measured at m = 48, direct 2.4-4.0%, bounce 2 6.1-9.7%, bounce 3 7.5-11.2%."""
    sim, _, dec = _scan(tmp_path, 48, scene="textured")
    for kind in KINDS:
        errors = _errors(sim, dec, kind)
        assert errors[0] < 0.05 and errors[1] < 0.12 and errors[2] < 0.14, (kind, errors)


def _high_frequency(image, width):
    """Energy of an image row less its moving average over ``width`` pixels."""
    row = image.mean(axis=0)
    smooth = np.convolve(row, np.ones(width) / width, mode="same")
    return np.linalg.norm((row - smooth)[width:-width])


def test_stripes_stay_in_the_direct_image(scans):
    """The projector's sharp stripes are direct light: bounce 2 carries no stripe pattern
    (its high-frequency energy relative to the photo's is as small as the truth's), and
    the direct image carries it all."""
    sim, _, dec = scans[48]
    truth = np.load(sim / "truth" / "photos" / "projector-bounces.npy").astype(np.float64)
    photo = _image(sim / "photos" / "projector.exr")
    width = 24
    reference = _high_frequency(photo, width)
    assert _high_frequency(truth[0], width) > 0.9 * reference          # the stripes are direct light
    est2 = _high_frequency(_image(dec / "projector" / "bounce-2.exr"), width) / reference
    true2 = _high_frequency(truth[1], width) / reference
    assert est2 < 0.05 and est2 < 3 * true2 + 0.01
    est1 = _high_frequency(_image(dec / "projector" / "bounce-1.exr"), width) / reference
    assert est1 == pytest.approx(1.0, abs=0.05)


def test_a_plane_of_light_is_fitted_exactly():
    """Analytic: inside each cell a frame that is a plane in (x, y) gives back its slopes,
    in units of the cell's size; a constant gives zero."""
    labels = np.full((20, 30), -1, np.int32)
    labels[:, :14] = 0
    labels[2:18, 14:29] = 1
    geometry = CellGeometry.from_labels(labels, 2)
    fit = fit_operator(geometry, 1)
    y, x = np.mgrid[:20, :30].astype(np.float64)
    slopes = {0: (0.5, -2.0), 1: (3.0, 0.25)}
    frame = np.zeros((20, 30))
    for cell, (a, b) in slopes.items():
        inside = labels == cell
        frame[inside] = 7.0 + a * x[inside] + b * y[inside]
    coefficients = (fit @ frame.ravel()).reshape(basis_terms(1), 2)
    for cell, (a, b) in slopes.items():
        np.testing.assert_allclose(coefficients[:, cell], np.array([a, b]) * geometry.size[cell], rtol=1e-12)
    assert np.abs(fit @ np.full(600, 3.0)).max() < 1e-12
    basis = geometry.basis(2)
    for term in basis:   # every basis function sums to zero over each cell
        assert np.abs(np.bincount(geometry.label, term, 2)).max() < 1e-9


def test_fine_operator_leaves_t_bit_for_bit(scans, tmp_path):
    sim, isf_dir, _ = scans[16]
    spots = isf_dir.parent / "spots"
    run("build-isf", sim / "hdr", spots, "-o", tmp_path / "bare", "--workers", 1, "--no-fine")
    assert not (tmp_path / "bare" / "fine").exists()
    assert np.array_equal(np.load(tmp_path / "bare" / "T.npy"), np.load(isf_dir / "T.npy"))
    manifest = json.loads((isf_dir / "fine" / "manifest.json").read_text())
    coefficients = np.load(isf_dir / "fine" / "coefficients.npy")
    assert coefficients.dtype == np.float32 and coefficients.shape == (2, 16, 16)
    assert manifest["inputs"]["T"].startswith("sha256:") and manifest["parameters"] == {"degree": 1}
    assert "fine/coefficients.npy" in json.loads((isf_dir / "manifest.json").read_text())["outputs"]


def test_samples_only_and_an_isf_without_the_fine_operator(scans, tmp_path):
    sim, isf_dir, _ = scans[16]
    photo = sim / "photos" / "room.exr"
    run("decompose", "--isf", isf_dir, photo, "-o", tmp_path / "a", "--no-cache", "--samples-only")
    assert not (tmp_path / "a" / "room" / "bounce-1.exr").exists()
    assert (tmp_path / "a" / "room" / "samples" / "bounce-1.exr").exists()
    bare = tmp_path / "isf"
    shutil.copytree(isf_dir, bare)
    shutil.rmtree(bare / "fine")
    result = run("decompose", "--isf", bare, photo, "-o", tmp_path / "b", "--no-cache")
    assert "no fine operator" in result.output and "m samples only" in result.output
    summary = json.loads((tmp_path / "b" / "room" / "summary.json").read_text())["full_resolution"]
    assert summary["written"] is False and "no fine operator" in summary["reason"]


def _refused(args, out, *words):
    result = run(*args, ok=False)
    assert result.exit_code != 0
    message = result.output.strip().splitlines()[-1]
    for w in words:
        assert w in message, message
    assert not out.exists() or not any(out.iterdir())
    return message


def test_a_changed_t_is_refused(scans, tmp_path):
    sim, isf_dir, _ = scans[16]
    changed = tmp_path / "isf"
    shutil.copytree(isf_dir, changed)
    T = np.load(changed / "T.npy")
    T[3, 5] *= 1.001
    np.save(changed / "T.npy", T)
    _refused(["decompose", "--isf", changed, sim / "photos" / "room.exr", "-o", tmp_path / "out", "--no-cache"],
             tmp_path / "out", "fine", "another T", "build-isf")


def test_changed_frames_are_refused(scans, tmp_path):
    """The fine operator records its frames' directory by the manifest ilt wrote there."""
    sim, isf_dir, _ = scans[16]
    hdr = sim / "hdr"
    manifest = json.loads((hdr / "manifest.json").read_text())
    saved = (hdr / "manifest.json").read_text()
    try:
        manifest["parameters"]["seed"] = 99
        (hdr / "manifest.json").write_text(json.dumps(manifest))
        _refused(["decompose", "--isf", isf_dir, sim / "photos" / "room.exr", "-o", tmp_path / "out", "--no-cache"],
                 tmp_path / "out", str(hdr), "changed")
    finally:
        (hdr / "manifest.json").write_text(saved)


def test_changed_frames_are_refused_in_a_moved_workspace(scans, tmp_path):
    """fine/ names its frames by their path from the ISF: the check travels with the scan."""
    sim, isf_dir, _ = scans[16]
    moved = tmp_path / "moved"
    shutil.copytree(isf_dir.parent, moved, ignore=shutil.ignore_patterns("dec"))
    manifest = json.loads((moved / "sim" / "hdr" / "manifest.json").read_text())
    manifest["parameters"]["seed"] = 99
    (moved / "sim" / "hdr" / "manifest.json").write_text(json.dumps(manifest))
    _refused(["decompose", "--isf", moved / "isf", moved / "sim" / "photos" / "room.exr", "-o", tmp_path / "out",
              "--no-cache"], tmp_path / "out", str(moved / "sim" / "hdr"), "changed")


def test_bad_photos_are_refused(scans, tmp_path):
    sim, isf_dir, _ = scans[16]
    photo = read_exr(sim / "photos" / "room.exr")[0][:, :, 0]
    small = tmp_path / "small.exr"
    write_exr(small, photo[:, :-3])
    _refused(["decompose", "--isf", isf_dir, small, "-o", tmp_path / "o1", "--no-cache"], tmp_path / "o1",
             str(small), "pixels")
    shifted = tmp_path / "shifted.exr"
    write_exr(shifted, photo, attributes={"ilt:pixel_origin": [0.5, 0.5], "ilt:pixel_scale": 2.0})
    _refused(["decompose", "--isf", isf_dir, shifted, "-o", tmp_path / "o3", "--no-cache"], tmp_path / "o3",
             str(shifted), "pixel mapping")
    holes = photo.copy()
    holes[2, 5] = np.nan
    holes[4, 9] = np.inf
    bad = tmp_path / "nan.exr"
    out = oiio.ImageOutput.create(str(bad))   # ilt's own writer refuses non-finite pixels
    assert out.open(str(bad), oiio.ImageSpec(holes.shape[1], holes.shape[0], 1, "float"))
    out.write_image(np.ascontiguousarray(holes[:, :, None], dtype=np.float32))
    out.close()
    _refused(["decompose", "--isf", isf_dir, bad, "-o", tmp_path / "o2", "--no-cache"], tmp_path / "o2",
             str(bad), "nan at pixel (x=5, y=2)", "2 non-finite values")


def test_saturated_pixels_are_left_out_and_counted(scans, tmp_path):
    import cv2

    sim, isf_dir, _ = scans[16]
    photo = tmp_path / "room.exr"
    shutil.copyfile(sim / "photos" / "room.exr", photo)
    image = _image(photo)
    mask = np.zeros(image.shape, np.uint8)
    mask[10:12, 100:110] = 255
    cv2.imwrite(str(photo.with_suffix(".saturated.png")), mask)
    result = run("decompose", "--isf", isf_dir, photo, "-o", tmp_path / "out", "--no-cache")
    assert "20 saturated pixels" in result.output
    out = tmp_path / "out" / "room"
    saturated = mask > 0
    assert np.all(_image(out / "coverage.exr")[saturated] == 0)
    np.testing.assert_array_equal(_image(out / "residual.exr")[saturated], image[saturated])
    for n in (1, 2):
        assert np.all(_image(out / f"bounce-{n}.exr")[saturated] == 0)
    summary = json.loads((out / "summary.json").read_text())["full_resolution"]
    assert summary["saturated_pixels"] == 20


def test_the_rim_takes_the_nearest_cells_indirect_light_up_to_the_photos():
    """Two flat cells on columns 0-19; columns 20-29 are the rim (within RIM_PX), 30-39
    beyond. A rim pixel takes each Phi_n of the nearest pixel inside (column 19 of its row)
    times s, the lesser of photo / Phi_0 and the photo's ratio to that pixel's, in [0, 1]:
    all of it under a bright photo; half of it where the photo holds half of Phi_0 and the
    pixel inside reads Phi_0 (rows 0-2); an eighth where the pixel inside reads
    8x the rim's photo (rows 3-5); none where the photo is dark. Bounce 1 is the rest, so
    the images still sum to the photo. Beyond the rim: no bounces, the residual is the photo."""
    from types import SimpleNamespace

    from ilt.decompose.fullres import RIM_COVERAGE, full_resolution
    from ilt.isf.fine import RIM_PX, FineOperator

    assert RIM_PX == 10
    labels = -np.ones((6, 40), np.int64)
    labels[:, :10], labels[:, 10:20] = 0, 1
    fine = FineOperator(None, CellGeometry.from_labels(labels, 2), 0, np.zeros((0, 2, 2), np.float32))
    bounces = np.array([[[600.0], [300.0]], [[60.0], [90.0]], [[12.0], [30.0]]])   # L1-L3 of each cell
    decomposition = SimpleNamespace(bounces=bounces, residual=np.array([[6.0], [12.0]]), count=3)
    phi0 = (90.0 + 30.0 + 12.0) / 60                       # cell 1's Phi_0 per pixel (60 px): 2.2
    photo = np.full((6, 40, 1), 7.0, np.float32)
    photo[:, :10] = 11.3
    photo[:3, 10:20], photo[3:, 10:20] = 2.2, 8.8
    photo[:, 20:23], photo[:, 23:26], photo[:, 26:30] = 100.0, 1.1, 0.0
    images = full_resolution(fine, photo, decomposition, np.ones(2))
    got = {k: v.reshape(6, 40).astype(np.float64) for k, v in images.items()}
    share = np.zeros((6, 10))
    share[:, :3], share[:3, 3:6], share[3:, 3:6] = 1.0, 0.5, 0.125
    rim = slice(20, 30)
    np.testing.assert_allclose(got["coverage"][0], [1.0] * 20 + [RIM_COVERAGE] * 10 + [0.0] * 10)
    for name, inside in (("indirect", phi0), ("bounce-2", 90.0 / 60), ("bounce-3", 30.0 / 60),
                         ("residual", 12.0 / 60)):
        np.testing.assert_allclose(got[name][:, rim], share * inside, rtol=1e-5)
        np.testing.assert_allclose(got[name][:, 19], inside, rtol=1e-5)
    np.testing.assert_allclose(got["bounce-1"][:, rim], photo[:, rim, 0] - got["indirect"][:, rim], rtol=1e-5, atol=1e-6)
    assert np.all(got["bounce-1"][:, 26:30] == 0) and np.all(got["bounce-1"][:, 30:] == 0)
    np.testing.assert_array_equal(got["residual"][:, 30:], 7.0)
    total = sum(got[f"bounce-{n}"] for n in (1, 2, 3)) + got["residual"]
    np.testing.assert_allclose(total, photo[:, :, 0], rtol=1e-5)


def test_no_pixel_holds_more_indirect_light_than_the_photo():
    """Two flat cells of 10 px, each with Phi_0 = 1 a pixel (L2, L3, r = 6, 3, 1). Cell 0's
    photo is dark on two pixels (background past a silhouette), 1.1 on two and 5 on six:
    the dark ones take no indirect light, the 1.1 ones 1.1, and the six the rest, c = 1.3
    each (2.2 + 6 c = 10), so the cell still holds its 10. Cell 1's photo, 0.5 a pixel, is
    less in all than its indirect light: each pixel takes the photo's, bounce 1 is 0. The
    later bounces and the residual are scaled by the same factor per pixel."""
    from types import SimpleNamespace

    from ilt.decompose.fullres import full_resolution
    from ilt.isf.fine import FineOperator

    labels = np.repeat([0, 1], 10)[None, :]
    fine = FineOperator(None, CellGeometry.from_labels(labels, 2), 0, np.zeros((0, 2, 2), np.float32))
    photo = np.array([[0, 0, 1.1, 1.1] + [5.0] * 6 + [0.5] * 10], np.float32)[:, :, None]
    totals = photo[0, :, 0].reshape(2, 10).sum(axis=1)
    bounces = np.array([[[totals[0] - 10.0], [totals[1] - 10.0]], [[6.0], [6.0]], [[3.0], [3.0]]])
    decomposition = SimpleNamespace(bounces=bounces, residual=np.array([[1.0], [1.0]]), count=3)
    report = {}
    got = {k: v.reshape(20).astype(np.float64)
           for k, v in full_resolution(fine, photo, decomposition, np.ones(2), report=report).items()}
    assert report == {"bounded_pixels": 12, "bound": "the photo"}      # the two dark pixels and all of cell 1
    factor = np.array([0, 0, 1.1, 1.1] + [1.3] * 6 + [0.5] * 10)
    np.testing.assert_allclose(got["indirect"], factor, rtol=1e-6)
    np.testing.assert_allclose(got["bounce-1"], photo[0, :, 0] - factor, rtol=1e-5, atol=1e-6)
    for name, share in (("bounce-2", 0.6), ("bounce-3", 0.3), ("residual", 0.1)):
        np.testing.assert_allclose(got[name], share * factor, rtol=1e-5)
    np.testing.assert_allclose(got["bounce-2"][:10].sum(), 6.0, rtol=1e-6)


def test_a_noisy_photo_keeps_its_noise_in_bounce_1():
    """Four flat cells of 32 x 32 px whose indirect light is 1 a pixel, under a photo of 1.1
    with 10% noise: bounded at the photo itself, every pixel where the noise reads under 1
    is cut (z < -0.91: 18% of them) and that noise carried into the later bounces; the
    photo's own noise, measured from its pixels (sigma within 20% of 0.11), widens the bound
    by 3 sigma and none is (z < -3.9)."""
    from types import SimpleNamespace

    from ilt.decompose.fullres import full_resolution, photo_noise_models
    from ilt.isf.fine import FineOperator

    labels = (np.arange(64)[:, None] // 32) * 2 + (np.arange(64)[None, :] // 32)
    fine = FineOperator(None, CellGeometry.from_labels(labels, 4), 0, np.zeros((0, 4, 4), np.float32))
    rng = np.random.default_rng(3)
    photo = (1.1 * (1 + 0.1 * rng.standard_normal((64, 64)))).astype(np.float32)[:, :, None]
    models = photo_noise_models(photo)
    assert models is not None and 0.8 * 0.11 < np.sqrt(models[0].pixel_variance(np.array([1.1])))[0] < 1.2 * 0.11
    totals = integrate(photo[:, :, 0], labels, 4)
    decomposition = SimpleNamespace(bounces=np.stack([totals - 1024.0, np.full(4, 614.4), np.full(4, 307.2)])[:, :, None],
                                    residual=np.full((4, 1), 102.4), count=3)
    for noise, most in ((None, None), (models, 0.0)):
        report = {}
        images = full_resolution(fine, photo, decomposition, np.ones(4), report=report, photo_noise=noise)
        if noise is None:
            assert 0.12 * 4096 < report["bounded_pixels"] < 0.25 * 4096
        else:
            assert report["bounded_pixels"] <= most * 4096
            assert report["bound"] == "the photo + 3 sigma of its own noise"
            np.testing.assert_allclose(images["indirect"][:, :, 0], 1.0, rtol=1e-5)
    # given as the function that measures it, the noise is measured only when a pixel is over the photo
    calls = []
    measure = lambda image: calls.append(image.shape) or photo_noise_models(image)   # noqa: E731
    full_resolution(fine, photo, decomposition, np.ones(4), report=report, photo_noise=measure)
    assert calls == [(64, 64, 1)] and report["bounded_pixels"] == 0
    full_resolution(fine, photo + 1.0, decomposition, np.ones(4), report=report, photo_noise=measure)
    assert calls == [(64, 64, 1)] and report == {"bounded_pixels": 0, "bound": "the photo"}


def test_a_path_tracers_noisy_photo_is_bounded_at_each_pixels_level_not_its_reading():
    """Four flat cells of 32 x 32 px at levels 1, 2, 2, 4 a pixel, whose indirect light is
    0.8 of it, under a photo of the level times Gamma(4, 1/4) (a path tracer's 4 samples:
    sigma half the light). The photo's noise model read at each pixel's own value would give
    the pixels that read low a margin as low and cut them (p + 3 sigma(p) under the indirect
    light: some 40 of them); read at the level the model was fitted on (the 5 x 5 mean),
    none is, and every bounce keeps its flat share."""
    from types import SimpleNamespace

    from ilt.decompose.fullres import full_resolution, photo_noise_models
    from ilt.isf.fine import FineOperator

    labels = (np.arange(64)[:, None] // 32) * 2 + (np.arange(64)[None, :] // 32)
    level = np.array([1.0, 2.0, 2.0, 4.0])
    fine = FineOperator(None, CellGeometry.from_labels(labels, 4), 0, np.zeros((0, 4, 4), np.float32))
    rng = np.random.default_rng(7)
    photo = (level[labels] * rng.gamma(4.0, 0.25, (64, 64))).astype(np.float32)[:, :, None]
    models = photo_noise_models(photo)
    assert models is not None
    own = photo[:, :, 0].astype(np.float64).ravel()
    indirect = 0.8 * level[labels].ravel()
    assert np.count_nonzero(own + 3 * np.sqrt(models[0].pixel_variance(own)) < indirect) >= 20
    totals = integrate(photo[:, :, 0], labels, 4)
    held = 1024 * 0.8 * level
    decomposition = SimpleNamespace(bounces=np.stack([totals - held, 0.6 * held, 0.3 * held])[:, :, None],
                                    residual=(0.1 * held)[:, None], count=3)
    report = {}
    images = full_resolution(fine, photo, decomposition, np.ones(4), report=report, photo_noise=models)
    assert report["bounded_pixels"] == 0
    np.testing.assert_allclose(images["indirect"][:, :, 0].ravel(), indirect, rtol=1e-5)
    np.testing.assert_allclose(images["bounce-2"][:, :, 0].ravel(), 0.6 * indirect, rtol=1e-5)


def test_a_noisy_photos_dark_background_beside_a_surface_takes_no_indirect_light():
    """One flat cell of 64 x 64 px, indirect light 1 a pixel; its photo is 4 times
    Gamma(16, 1/16) a pixel but for 16 columns of dark background past a silhouette. The
    margin is read at the 5 x 5 median, which keeps the background's own level beside the
    bright columns (a 5 x 5 mean there is up to 0.4 of theirs, sigma 0.4: a margin of 1.2
    that would leave the background its indirect light): the background holds none."""
    from types import SimpleNamespace

    from ilt.decompose.fullres import full_resolution, photo_noise_models
    from ilt.isf.fine import FineOperator

    labels = np.zeros((64, 64), np.int64)
    fine = FineOperator(None, CellGeometry.from_labels(labels, 1), 0, np.zeros((0, 1, 1), np.float32))
    photo = 4.0 * np.random.default_rng(11).gamma(16.0, 1 / 16, (64, 64))
    photo[:, :16] = 0.0
    photo = photo.astype(np.float32)[:, :, None]
    models = photo_noise_models(photo)
    assert models is not None
    total = float(photo.sum())
    decomposition = SimpleNamespace(bounces=np.array([[[total - 4096.0]], [[4096.0 * 0.6]], [[4096.0 * 0.3]]]),
                                    residual=np.array([[409.6]]), count=3)
    report = {}
    images = full_resolution(fine, photo, decomposition, np.ones(1), report=report, photo_noise=models)
    indirect = images["indirect"][:, :, 0]
    assert report["bounded_pixels"] >= 16 * 64
    np.testing.assert_array_equal(indirect[:, :16], 0.0)
    np.testing.assert_allclose(indirect.sum(), 4096.0, rtol=1e-5)     # the cell keeps its light


def test_the_rim_is_every_pixel_near_a_cell_and_its_nearest_pixel_inside():
    """Against brute force on random cells: the rim is the pixels outside every cell within
    RIM_PX (chessboard) of one, and each is paired with an inside pixel at its least
    Euclidean distance."""
    from ilt.isf.fine import RIM_PX, rim

    rng = np.random.default_rng(5)
    labels = -np.ones((50, 70), np.int64)
    for k in range(4):
        y, x = rng.integers(0, 45), rng.integers(0, 60)
        labels[y:y + rng.integers(2, 8), x:x + rng.integers(2, 12)] = k
    geometry = CellGeometry.from_labels(labels, 4)
    pixels, nearest = rim(geometry)
    yx = np.column_stack(np.divmod(np.arange(labels.size), 70))
    inside = yx[geometry.inside]
    chess = np.abs(yx[:, None, :] - inside[None]).max(axis=2).min(axis=1)
    expected = np.flatnonzero((chess >= 1) & (chess <= RIM_PX))
    np.testing.assert_array_equal(pixels, expected)
    best = np.linalg.norm(yx[pixels][:, None, :] - inside[None], axis=2).min(axis=1)
    np.testing.assert_allclose(np.linalg.norm(yx[pixels] - inside[nearest], axis=1), best)
    full = CellGeometry.from_labels(np.zeros((4, 4), np.int64), 1)
    assert rim(full)[0].size == 0 and rim(CellGeometry.from_labels(-np.ones((4, 4), np.int64), 1))[0].size == 0
