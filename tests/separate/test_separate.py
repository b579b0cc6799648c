"""Nayar et al.'s max/min separation: exact on its own model, on the simulator, and bad input refused."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exr import read_exr
from ilt.separate.nayar import direct_global
from ilt.sim.scene import make_scene
from ilt.workspace.simulate import write_simulation


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], prog_name="ilt")


@pytest.mark.parametrize("black", [0.0, 0.1])
def test_their_model_is_inverted_exactly(black):
    """L_k = Ld (lit_k + b (1 - lit_k)) + (1 + b) / 2 Lg, every pixel lit in one pattern and dark in another."""
    rng = np.random.default_rng(0)
    Ld, Lg = rng.uniform(0, 1, (6, 5)), rng.uniform(0, 1, (6, 5))
    lit = np.zeros((4, 6, 5))
    lit[rng.integers(0, 2, (6, 5)) * 2, np.arange(6)[:, None], np.arange(5)] = 1   # lit in pattern 0 or 2
    lit[1] = 1 - lit[0] - lit[2]
    stack = Ld * (lit + black * (1 - lit)) + (1 + black) / 2 * Lg
    direct, global_ = direct_global(stack, black)
    np.testing.assert_allclose(direct, Ld, atol=1e-12)
    np.testing.assert_allclose(global_, Lg, atol=1e-12)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    root = tmp_path_factory.mktemp("nayar")
    return write_simulation(make_scene("m", 32), root / "sim", {"scene": "m"}, n_bounces=30, patterns=4)


def test_the_simulated_pattern_photos_separate_near_the_truth(simulated, tmp_path):
    """The M under 4 shifted stripe patterns: direct within 0.2 of the true bounce 1 (the stripes are
    not much finer than the light between the M's facets varies: docs/theory.md), the sum near the photo."""
    photos = sorted((simulated / "photos" / "patterns").glob("stripes-*.exr"))
    assert len(photos) == 4
    result = run("separate", *photos, "-o", tmp_path / "sep", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["patterns"] == 4
    direct, attributes = read_exr(tmp_path / "sep" / "direct.exr")
    global_, _ = read_exr(tmp_path / "sep" / "global.exr")
    assert attributes["ilt:quantity"] == "direct" and (tmp_path / "sep" / "preview.png").exists()
    samples = np.loadtxt(simulated / "samples.csv", delimiter=",", skiprows=1, usecols=(1, 2)).astype(int)
    at = (samples[:, 1], samples[:, 0], 0)
    truth = np.load(simulated / "truth" / "photos" / "projector-full-bounces.npy")
    full = np.load(simulated / "photos" / "projector-full.npy")
    assert np.linalg.norm(direct[at] - truth[0]) / np.linalg.norm(truth[0]) < 0.2
    assert np.linalg.norm(direct[at] + global_[at] - full) / np.linalg.norm(full) < 0.1
    assert (direct >= 0).all()


def test_bad_inputs_are_one_line_and_nothing_written(simulated, tmp_path):
    patterns = simulated / "photos" / "patterns"
    out = tmp_path / "out"
    cases = [
        ([patterns / "stripes-0.exr"], "at least 2 pattern photos"),
        ([patterns / "stripes-0.exr", patterns / "stripes-1.npy"], "mixed kinds"),
        ([patterns / "stripes-0.exr", patterns / "stripes-0.exr"], "given twice"),
        ([patterns / "stripes-0.npy", simulated / "truth" / "photos" / "room-bounces.npy"], "differs from"),
        ([patterns / "stripes-0.exr", tmp_path / "missing.exr"], "missing.exr: no such file"),
    ]
    for photos, message in cases:
        result = run("separate", *photos, "-o", out)
        assert result.exit_code != 0 and message in result.output, (message, result.output)
        assert len([line for line in result.output.splitlines() if line.startswith("ilt: error")]) == 1
        assert not out.exists()
    result = run("separate", patterns / "stripes-0.exr", patterns / "stripes-1.exr", "-o", patterns)
    assert result.exit_code != 0 and "where the pattern photos are" in result.output
    assert sorted(p.name for p in patterns.iterdir()) == sorted(
        [f"stripes-{k}.{ext}" for k in range(4) for ext in ("exr", "npy")])
