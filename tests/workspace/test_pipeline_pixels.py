"""Pixel coordinates through the real pipeline: capture -> merge -> centroids -> build-isf
-> decompose, on half-resolution green HDR frames.

Spots and samples must come out in full-frame sensor pixels (DESIGN.md sec. 3), while
cells and the integration of frames stay on the HDR frame grid.
"""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.hdr.bracket import list_beams, read_beam
from ilt.io.exr import read_exr
from ilt.io.frames import PixelMapping, open_hdr_directory, read_frame
from ilt.io.raw import read_green
from ilt.isf.directory import load_isf
from ilt.sim.render import render_scene
from ilt.spots.stage import read_shortest_exposure
from ilt.spots.table import read_spots
from tests.capture_helpers import toml_text

PX_PER_BEAM, ROWS, BEAMS = 32.0, 32, 8
BRACKET = {"shutter": ["1/15", "1/250", "1/4000"], "aperture": 1.2,
           "extra": [{"shutter": "1/4000", "aperture": 16}]}
HALF_RES = PixelMapping((0.5, 0.5), 2.0)


def _ok(args):
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    return result


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("pixels")
    (d / "rig.toml").write_text(toml_text(camera={"px_per_beam": PX_PER_BEAM, "rows": ROWS}, bracket=BRACKET))
    _ok(["capture", str(d / "rig.toml"), "-o", str(d / "capture")])
    _ok(["merge", str(d / "capture"), "-o", str(d / "hdr")])
    _ok(["centroids", str(d / "hdr"), "-o", str(d / "spots"), "--workers", "1"])
    _ok(["build-isf", str(d / "hdr"), str(d / "spots"), "-o", str(d / "isf"), "--workers", "1"])
    truth = render_scene("m", beams=BEAMS, px_per_beam=PX_PER_BEAM, rows=ROWS).centres
    return d, truth


def _xy(path):
    _, spots = read_spots(path)
    assert not any(s.flags for s in spots), [s.flags for s in spots]
    return np.array([[s.x, s.y] for s in spots])


def test_merged_frames_carry_their_mapping(run):
    d, _ = run
    hdr = open_hdr_directory(d / "hdr")
    assert hdr.mapping == HALF_RES
    height, width = hdr.frame_shape
    assert (height, width) == (ROWS // 2, read_green(next((d / "capture").glob("beam-*/frame-*")))[0].shape[1])


def test_spots_from_hdr_frames_are_in_full_frame_pixels(run):
    d, truth = run
    xy = _xy(d / "spots" / "spots.csv")
    assert np.abs(xy - truth).max() < 0.5
    assert np.median(np.diff(xy[:, 0])) == pytest.approx(PX_PER_BEAM, abs=0.5)   # not half of it
    manifest = json.loads((d / "spots" / "manifest.json").read_text())
    assert manifest["pixel_mapping"] == HALF_RES.as_dict()
    assert PixelMapping.from_attributes(read_exr(d / "spots" / "sum.exr")[1], "sum") == HALF_RES


def test_spots_from_the_capture_directory_use_the_shortest_exposure(run, tmp_path):
    d, truth = run
    _ok(["centroids", str(d / "capture"), "-o", str(tmp_path / "spots"), "--workers", "1"])
    xy = _xy(tmp_path / "spots" / "spots.csv")
    assert np.abs(xy - truth).max() < 0.5
    beam = read_beam(list_beams(d / "capture")[0])
    assert beam.dark is not None
    frame, mapping, saturation = read_shortest_exposure(beam.beam_dir)
    shortest = next(r for r in beam.frames if r.f_number == "16")
    expected = read_green(beam.path(shortest), shortest.exposure_time, shortest.f_number)[0] \
        - read_green(beam.path(beam.dark), beam.dark.exposure_time, beam.dark.f_number)[0]
    assert mapping == HALF_RES and saturation > 0
    np.testing.assert_allclose(frame, expected, rtol=1e-5, atol=1e-3)


def test_isf_samples_are_full_frame_and_cells_stay_on_the_hdr_grid(run):
    d, truth = run
    isf = load_isf(d / "isf")
    assert np.abs(isf.samples - truth).max() < 0.5
    assert isf.mapping == HALF_RES and isf.cells.shape == open_hdr_directory(d / "hdr").frame_shape
    cx = isf.grid_samples.round().astype(int)
    assert (isf.cells[cx[:, 1], cx[:, 0]] == np.arange(isf.m)).all()   # every spot lies in its own cell
    assert PixelMapping.from_attributes(read_exr(d / "isf" / "cells.exr")[1], "cells") == HALF_RES


def test_decompose_integrates_a_merged_photo_over_the_same_cells(run):
    d, _ = run
    photo = sorted((d / "hdr").glob("beam-*.exr"))[3]
    _ok(["decompose", "--isf", str(d / "isf"), str(photo), "-o", str(d / "out"), "--no-cache"])
    out = d / "out" / photo.stem
    total = np.load(out / "bounces.npy").sum(axis=0) + np.load(out / "residual.npy")
    isf = load_isf(d / "isf")
    np.testing.assert_allclose(total, isf.T[:, 3] * isf.scales[3], rtol=1e-6)
    assert PixelMapping.from_attributes(read_exr(out / "samples" / "photo.frame.exr")[1], "photo") == HALF_RES


def test_point_sampling_reads_the_grid_pixel_of_each_spot(run, tmp_path):
    d, _ = run
    _ok(["build-isf", str(d / "hdr"), str(d / "spots"), "-o", str(tmp_path / "isf"), "--sampling", "point",
         "--workers", "1"])
    isf = load_isf(tmp_path / "isf")
    px = np.floor(isf.grid_samples + 0.5).astype(int)
    frame = read_frame(sorted((d / "hdr").glob("beam-*.exr"))[2])
    np.testing.assert_allclose(isf.T[:, 2] * isf.scales[2], frame[px[:, 1], px[:, 0]], rtol=1e-6)
