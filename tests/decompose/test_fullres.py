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


def test_pixels_close_and_cells_integrate_to_the_sample_bounces(scans):
    """photo = bounce 1 + ... + bounce N + residual at every pixel, and each full-resolution
    image integrates over every cell to its sample-level vector (the cell-consistency
    identity: the basis has zero sum over each cell, the constant is T's own)."""
    sim, isf_dir, dec = scans[48]
    isf = load_isf(isf_dir)
    for kind in KINDS:
        out = dec / kind
        photo = _image(sim / "photos" / f"{kind}.exr")
        images = np.stack([_image(out / f"bounce-{n}.exr") for n in range(1, 9)])
        residual = _image(out / "residual.exr")
        scale = np.abs(photo).max()
        assert np.abs(images.sum(axis=0) + residual - photo).max() < 1e-6 * scale
        bounces = np.load(out / "bounces.npy")
        for n in range(8):
            np.testing.assert_allclose(integrate(images[n], isf.cells, isf.m), bounces[n],
                                       atol=1e-6 * np.abs(bounces[0]).max())
        np.testing.assert_allclose(integrate(residual, isf.cells, isf.m), np.load(out / "residual.npy"),
                                   atol=1e-6 * np.abs(bounces[0]).max())
        np.testing.assert_allclose(photo - images[0], _image(out / "indirect.exr"), atol=1e-6 * scale)


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
