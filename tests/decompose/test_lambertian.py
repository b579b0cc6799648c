"""decompose refuses a T that fails the theorem's checks, in one line and writing nothing, unless told."""

import json

import numpy as np
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exr import read_exr
from ilt.isf.directory import write_isf
from ilt.sim.scene import make_scene
from ilt.workspace.simulate import write_simulation


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], prog_name="ilt")


def _error_lines(result) -> list[str]:
    return [line for line in result.output.splitlines() if line.startswith("ilt: error")]


def test_a_glossy_scene_is_refused_with_one_line_and_nothing_written(tmp_path):
    isf = write_simulation(make_scene("m", 16), tmp_path / "glossy", {"scene": "m"}, n_bounces=3, gloss=0.5)
    verdict = json.loads((isf / "lambertian.json").read_text())
    assert verdict["verdict"] == "not lambertian" and verdict["excess"] > verdict["tolerance"]
    out = tmp_path / "out"
    result = run("decompose", "--isf", isf, isf / "photos" / "flashlight.npy", "-o", out, "--no-cache")
    assert result.exit_code != 0
    (line,) = _error_lines(result)
    assert "lambertian.json: not lambertian" in line and "reciprocity residual" in line and "glossy" in line
    assert "--accept-non-lambertian" in line
    assert not out.exists()

    result = run("decompose", "--isf", isf, isf / "photos" / "flashlight.exr", "-o", out, "--no-cache",
                 "--accept-non-lambertian")
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "flashlight" / "summary.json").read_text())
    assert summary["lambertian"]["verdict"] == "not lambertian" and summary["lambertian"]["accepted"] is True
    _, attributes = read_exr(out / "flashlight" / "samples" / "bounce-1.exr")
    assert attributes["ilt:lambertian"] == "not lambertian"


def test_a_diverging_series_is_refused_unless_accepted(tmp_path):
    """A with spectral radius 1.5 (albedo "1.5"): I - A is invertible, T is no physical scene's."""
    m = 12
    A = 1.5 * np.full((m, m), 1 / (m - 1))
    np.fill_diagonal(A, 0)
    T = np.linalg.inv(np.eye(m) - A)
    isf = tmp_path / "isf"
    isf.mkdir()
    samples = np.stack([np.arange(m) * 2.0, np.zeros(m)], axis=1)
    write_isf(isf, T / np.linalg.norm(T, axis=0), samples, (1, m), (1, 2 * m))
    np.save(tmp_path / "photo.npy", np.ones(m))
    result = run("decompose", "--isf", isf, tmp_path / "photo.npy", "-o", tmp_path / "out", "--no-cache")
    assert result.exit_code != 0
    (line,) = _error_lines(result)
    assert "spectral radius of A = I - C1 is 1.5 >= 1" in line and "glossy" in line
    assert not (tmp_path / "out").exists()
    result = run("decompose", "--isf", isf, tmp_path / "photo.npy", "-o", tmp_path / "out", "--no-cache",
                 "--accept-non-lambertian")
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "out" / "photo" / "summary.json").read_text())
    assert summary["lambertian"]["accepted"] is True and summary["lambertian"]["spectral_radius_A"] > 1.49
