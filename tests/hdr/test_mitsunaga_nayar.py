"""Mitsunaga-Nayar calibration against simulated brackets with a known response."""

import json

import numpy as np
from click.testing import CliRunner

from ilt.cli import cli
from ilt.hdr.mitsunaga_nayar import fit_response, usable_samples
from ilt.sim.sensor import SensorModel, expose, write_bracket, write_ldr


def _response(x):
    return x ** (1 / 2.2) * (1.1 - 0.1 * x)  # monotonic, response(1) = 1


def _true_inverse(grid):
    xx = np.linspace(0, 1, 200001)
    return np.interp(grid, _response(xx), xx)


def _scene(h=120, w=200):
    return np.logspace(2, 6, w)[None, :].repeat(h, 0)


LDR = SensorModel(width=200, height=120, black_level=0, white_level=255, bits=8, gain=60.0,
                  read_noise=30.0, response=_response, colour_scale=(1, 1, 1))
TIMES = [1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15]


def test_non_linear_8bit_response_within_half_a_percent():
    rng = np.random.default_rng(0)
    images = [expose(_scene(), t, 1.0, LDR, rng) / 255.0 for t in TIMES]
    valid = usable_samples(images, 3 / 255, 254 / 255, 254.5 / 255)
    fit = fit_response(images, np.array(TIMES), valid, pin_span=True)
    grid = np.linspace(0, 1, 1001)
    assert np.abs(fit(grid) - _true_inverse(grid)).max() <= 0.005
    assert fit.converged and fit(np.array(1.0)) == 1.0


def test_linear_raw_ratios_within_0p1_percent_from_nominal_4_percent_off(tmp_path):
    rng = np.random.default_rng(1)
    sensor = SensorModel(width=400, height=240)
    true = [2.0**-k for k in range(13, 5, -1)]
    nominal = [t * (1 + d) for t, d in zip(true, rng.uniform(-0.04, 0.04, len(true)))]
    bracket = [(t, 1.2, f"{n:.8g}") for t, n in zip(true, nominal)]
    write_bracket(tmp_path / "beam-00000", _scene(120, 200) * 10, bracket, sensor, rng)
    out = tmp_path / "response.json"
    result = CliRunner().invoke(cli, ["calibrate", str(tmp_path / "beam-00000"), "-o", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["kind"] == "raw" and data["coefficients"][0] == 0.0
    truth = np.array(true[1:]) / np.array(true[:-1])
    assert np.abs(np.array(data["ratios"]) / truth - 1).max() < 0.001
    assert np.abs(np.array(data["nominal_ratios"]) / truth - 1).max() > 0.01
    assert data["linearity_error"] <= 0.002
    assert out.with_suffix(".png").exists()


def test_calibrate_8bit_tiff_files_through_the_cli(tmp_path):
    rng = np.random.default_rng(2)
    files = [write_ldr(tmp_path / f"f{k}.tif", _scene(), t, 1.0, LDR, rng) for k, t in enumerate(TIMES)]
    out = tmp_path / "r.json"
    result = CliRunner().invoke(cli, ["calibrate", *map(str, files), "-o", str(out), "--no-plot"])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["kind"] == "ldr"
    c = np.array(data["coefficients"])
    grid = np.linspace(0, 1, 1001)
    assert np.abs(np.polynomial.polynomial.polyval(grid, c) - _true_inverse(grid)).max() <= 0.005


def test_calibrate_refuses_missing_times(tmp_path):
    import cv2

    rng = np.random.default_rng(3)
    files = []
    for k, t in enumerate(TIMES[:3]):
        frame = expose(_scene(), t, 1.0, LDR, rng).astype(np.uint8)
        cv2.imwrite(str(tmp_path / f"f{k}.png"), frame)
        files.append(str(tmp_path / f"f{k}.png"))
    result = CliRunner().invoke(cli, ["calibrate", *files, "-o", str(tmp_path / "r.json")])
    assert result.exit_code == 1 and "f0.png" in result.output and "--times" in result.output
    assert not (tmp_path / "r.json").exists()
