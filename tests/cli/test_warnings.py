"""Real problems still warn, each in one line that says what to look at: a noisy T, a
glossy scene (a wrong spot: tests/workspace/test_pipeline.py). Healthy runs print no
WARNING: tests/cli/test_rough_edges.py (the tutorial and the README's example) and
test_commands.py (the demo)."""

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def warnings(result) -> list[str]:
    return [line for line in result.stderr.splitlines() if "WARNING" in line]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    matte = run("simulate", "m", "--beams", 64, "-o", root / "matte")
    glossy = run("simulate", "m", "--beams", 64, "--gloss", 0.4, "-o", root / "glossy")
    assert matte.exit_code == 0 and glossy.exit_code == 0
    return root, matte, glossy


def test_an_exact_scene_decomposes_without_a_warning(scenes, tmp_path):
    root, matte, _ = scenes
    assert warnings(matte) == []
    result = run("decompose", "--isf", root / "matte", root / "matte" / "photos" / "flashlight.npy", "-o",
                 tmp_path / "out", "--no-cache")
    assert result.exit_code == 0 and warnings(result) == [], result.stderr
    assert "not judged against their noise (the noise of T is not known" in result.stderr


def test_a_noisy_t_warns_once_per_photo_that_its_bounces_are_noisy(scenes, tmp_path):
    """T + N(0, 1e-2) on its unit columns (the noise measured from T's own negative
    entries): the negatives are within that noise and are not warned of; the noise is."""
    root, _, _ = scenes
    noisy = tmp_path / "noisy"
    noisy.mkdir()
    T = np.load(root / "matte" / "T.npy")
    T = T + np.random.default_rng(1).normal(scale=1e-2, size=T.shape)
    np.save(noisy / "T.npy", T / np.linalg.norm(T, axis=0))
    photo = root / "matte" / "photos" / "flashlight.npy"
    result = run("decompose", "--isf", noisy / "T.npy", photo, "-o", tmp_path / "out", "--no-cache")
    assert result.exit_code == 0, result.output
    (line,) = warnings(result)
    assert line.startswith(f"ilt: WARNING: {photo}: bounce") and " noisy: " in line and "of its signal" in line
    assert "negatives" not in line


def test_a_glossy_scene_warns_at_simulate_is_refused_and_marked_when_accepted(scenes, tmp_path):
    root, _, glossy = scenes
    (line,) = warnings(glossy)
    assert "reciprocity: not lambertian" in line
    photo = root / "glossy" / "photos" / "flashlight.npy"
    refused = run("decompose", "--isf", root / "glossy", photo, "-o", tmp_path / "out", "--no-cache")
    assert refused.exit_code != 0 and "not lambertian" in refused.stderr and not (tmp_path / "out").exists()
    accepted = run("decompose", "--isf", root / "glossy", photo, "-o", tmp_path / "out", "--no-cache",
                   "--accept-non-lambertian")
    assert accepted.exit_code == 0
    lines = warnings(accepted)
    assert len(lines) == 2 and "writing the bounces as asked" in lines[0]
    assert " hold negatives " in lines[1] and "% of bounce" in lines[1] and "(worst: bounce" in lines[1]
