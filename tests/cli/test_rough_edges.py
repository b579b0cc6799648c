"""What a new user hits first: the tutorial as written, missing inputs, sizes that cannot
fit, bounds on options, help texts, the ISF manifest after a dropped beam (issue 14)."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from ilt.capture.plan import planned_beams
from ilt.cli import cli
from ilt.isf.directory import load_isf, write_isf
from ilt.isf.layout import vector_to_image
from ilt.sim import memory
from tests import ROOT


def run(*args, cwd=None):
    """``ilt ARGS`` in-process, in ``cwd``; the click result."""
    old = os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        return CliRunner().invoke(cli, [str(a) for a in args], prog_name="ilt")
    finally:
        os.chdir(old)


def tutorial_blocks(*sections: str) -> list[str]:
    """The ```bash blocks of docs/tutorial.md's sections (numbered '## 2.' ...), in order."""
    text = (ROOT / "docs" / "tutorial.md").read_text()
    parts = re.split(r"^## ", text, flags=re.M)
    blocks = []
    for number in sections:
        (part,) = [p for p in parts if p.startswith(f"{number}. ")]
        blocks += re.findall(r"```bash\n(.*?)```", part, flags=re.S)
    return blocks


def test_tutorial_sections_2_and_3_run_as_written(tmp_path):
    """§2 then §3 in one shell, top to bottom: every command exits 0 (set -e, the failing one
    named) and the files the comments promise are there."""
    blocks = tutorial_blocks("2", "3")
    assert len(blocks) == 2
    script = "set -eo pipefail\ntrap 'echo \"tutorial command failed: $BASH_COMMAND\" >&2' ERR\n" + "\n".join(blocks)
    # the venv's ilt and python first on PATH, as after '. .venv/bin/activate'
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "ILT_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    # a healthy run, the README's example among it (section 3 runs configs/sim.toml): nothing to act on,
    # and the lines name the files the user gets, not the stages' temporaries
    assert "WARNING" not in done.stderr, [line for line in done.stderr.splitlines() if "WARNING" in line]
    assert ".tmp-" not in done.stderr, [line for line in done.stderr.splitlines() if ".tmp-" in line]
    assert "scan2/decompose/room (computed all" in done.stderr
    scan = tmp_path / "scan"
    # §2: "32 beams x 11 exposures + dark -> capture/"
    beams = sorted((scan / "capture").glob("beam-*"))
    assert len(beams) == 32
    assert len(list(beams[10].glob("frame-*.dng"))) == 11 and (beams[10] / "dark.dng").is_file()
    assert len(list((scan / "hdr").glob("beam-*.exr"))) == 32
    for f in ("spots/spots.csv", "spots/overlay.png", "isf/T.npy", "photo.exr", "report/index.html"):
        assert (scan / f).is_file(), f
    photo = scan / "decompose" / "photo"
    for f in ("bounce-1.exr", "coverage.exr", "bounces.npy", "preview.png", "summary.json"):
        assert (photo / f).is_file(), f
    assert (photo / "samples").is_dir()
    # §3: every stage with photos, then nothing to do, then merge stale after the margin edit
    scan2 = scan / "scan2"
    for kind in ("flashlight", "room", "projector"):
        assert (scan2 / "photos" / f"{kind}.exr").is_file()
        assert (scan2 / "decompose" / kind / "bounce-1.exr").is_file()
    assert (scan2 / "report" / "index.html").is_file()
    assert "every stage was up to date" in done.stderr
    assert re.search(r"merge\s+stale: parameter margin changed \(0\.03 -> 0\.05\)", done.stdout + done.stderr)
    assert json.loads((scan2 / "hdr" / ".stage.json").read_text())["parameters"]["margin"] == 0.05


def test_simulate_refuses_a_scene_larger_than_memory_in_one_line():
    result = run("simulate", "m", "--beams", 400000, "-o", "never-written")
    assert result.exit_code == 1
    line = result.output.strip()
    assert "\n" not in line and line.startswith("ilt: error: scene 'm' with 400000 beams needs about ")
    assert re.search(r"needs about [\d.e+]+ GiB of memory, [\d.e+]+ GiB is available", line)
    assert not Path("never-written").exists()


def test_rendered_scene_memory_counts_the_fine_patches():
    # 64 beams x 16 fine patches = 1024 patches of the M: (1024, 1024) float64 matrices
    assert memory.render_bytes("m", 64, 16, 32.0, 4) == memory.MATRICES_AT_PEAK * 8 * 1024**2
    assert memory.render_bytes("m", 64, 32, 32.0, 4) == 4 * memory.render_bytes("m", 64, 16, 32.0, 4)
    assert memory.scene_patches("occluded", 1024) == 1536 and memory.scene_patches("box", 192) == 192


def test_capture_refuses_an_unknown_scene_and_a_huge_plan_before_making_capture(tmp_path):
    text = (ROOT / "configs" / "sim.toml").read_text()
    (tmp_path / "scene.toml").write_text(text.replace('scene = "m"', 'scene = "mm"'))
    (tmp_path / "huge.toml").write_text(re.sub(r"(?m)^count = 32", "count = 100000000", text))
    result = run("capture", "scene.toml", cwd=tmp_path)
    assert result.exit_code == 1
    assert result.output.strip() == "ilt: error: scene.toml: [camera] scene 'mm' unknown (known: m, textured, occluded, box)"
    result = run("capture", "huge.toml", cwd=tmp_path)
    assert result.exit_code == 1 and "for 100000000 beams needs about" in result.output
    assert not (tmp_path / "capture").exists()


def test_planned_beams_counts_without_building_the_plan():
    from ilt.capture.config import PlanConfig

    assert planned_beams(PlanConfig(kind="line", count=10**8)) == 10**8
    assert planned_beams(PlanConfig(kind="grid", shape=(18, 6))) == 108
    assert planned_beams(PlanConfig(kind="list", points=((0.0, 0.0), (1.0, 0.0)))) == 2


@pytest.mark.parametrize("command", [["decompose", "photo.exr"], ["simulate", "m", "-o", "x"], ["bench"]])
def test_bounces_has_an_upper_bound(command):
    result = run(*command, "--bounces", 100000000)
    assert result.exit_code == 2 and "100000000 is not in the range 1<=x<=1000" in result.output
    help_text = run(command[0], "--help").output
    assert "--bounces" in help_text and "at most 1000" in " ".join(help_text.split())


@pytest.mark.parametrize("args, message", [
    (["build-isf"], "ilt: error: hdr: no such directory (the HDR frames); run 'ilt merge' first, or give HDR_DIR"),
    (["centroids"], "ilt: error: hdr: no such directory (the HDR frames); run 'ilt merge' first, or give HDR_DIR"),
    (["merge"], "ilt: error: capture: no such directory (the capture); run 'ilt capture' first, or give CAPTURE_DIR"),
    (["capture", "nope.toml"], "ilt: error: nope.toml: no such rig config; give a rig TOML"),
    (["capture"], "ilt: error: rig.toml: no such rig config; give a rig TOML"),
    (["decompose", "photo.exr"], "ilt: error: isf: no such file"),
])
def test_an_empty_directory_gets_one_line_naming_what_is_missing(tmp_path, args, message):
    result = run(*args, cwd=tmp_path)
    assert result.exit_code == 1
    assert result.output.startswith(message) and result.output.count("\n") == 1
    assert "Errno" not in result.output


def test_help_texts_agree_with_usage_lines():
    def usage(command):
        return run(command, "--help").output.splitlines()[0]

    assert usage("calibrate") == "Usage: ilt calibrate [OPTIONS] IMAGES_OR_DIR..."
    assert usage("merge") == "Usage: ilt merge [OPTIONS] [CAPTURE_DIR | RAW_FILES...]"
    build = run("build-isf", "--help").output
    assert "OUTPUT" not in build.split("Options:")[0] and "(-o, default WORKSPACE/isf)" in " ".join(build.split())
    # one -j/--workers option, all cores by default, in every per-beam stage
    for command in ("merge", "centroids", "build-isf"):
        assert "-j, --workers" in run(command, "--help").output
        (option,) = [p for p in cli.commands[command].params if p.name == "workers"]
        assert option.get_default(click.Context(cli.commands[command])) == (os.cpu_count() or 1)


def test_isf_with_a_dropped_beam_says_plan_and_kept_beams_and_its_strips_show_the_gap(tmp_path):
    """A 1 x 8 plan with beam 3 dropped: 7 rows of T, the plan's 8 and the gap in the
    manifest, and beam 3's cell of a sample strip left empty."""
    beams = [j for j in range(8) if j != 3]
    samples = np.column_stack([np.arange(7) * 4.0, np.zeros(7)])
    fields = write_isf(tmp_path, np.eye(7), samples, (1, 8), (4, 32), beams=beams)
    assert fields["m"] == 7 and fields["plan_m"] == 8 and fields["layout"] == [1, 8]
    assert fields["dropped_beams"] == [3]
    (tmp_path / "manifest.json").write_text(json.dumps(fields))
    isf = load_isf(tmp_path)
    strip = vector_to_image(np.arange(1.0, 8.0), isf.layout, isf.beams)
    assert strip.shape == (1, 8)
    np.testing.assert_array_equal(strip[0], [1, 2, 3, 0, 4, 5, 6, 7])
