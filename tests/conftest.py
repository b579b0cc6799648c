"""Fixtures shared by the test folders."""

import json

import pytest
from click.testing import CliRunner

from ilt.cli import cli
from tests.capture_helpers import SMALL_RIG


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A workspace of SMALL_RIG after one ``ilt run``, every stage run (one per module:
    its tests may change it)."""
    root = tmp_path_factory.mktemp("ws")
    (root / "small.toml").write_text(SMALL_RIG)
    result = CliRunner().invoke(cli, ["run", str(root / "small.toml"), "-w", str(root / "ws"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert [s["stage"] for s in summary] == ["capture", "merge", "centroids", "build-isf", "photos", "decompose"]
    assert all(s["ran"] for s in summary)
    return root / "ws"
