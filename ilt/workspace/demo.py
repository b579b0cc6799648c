"""``ilt demo``: the paper's experiments on built-in simulated scenes, end to end.

For the "M" scene (paper Fig. 3-6) and the box (Fig. 7-9):

1. the whole rig, simulated: ``ilt run`` in the workspace ``OUT/<scene>/`` drives the
   emulated pan-tilt unit on a pseudo-terminal and the simulated camera writing DNG
   brackets, merges, finds the spots, builds T and decomposes the photos captured
   under the simulator's illuminations; ``ilt report`` draws its figures;
2. the exact-ISF experiment of Fig. 5 (``OUT/<scene>/exact/``): the exact T of the
   scene, its Cn T against the exact truth, also with the paper's forward tracer
   truncated at 7 bounces.

``OUT/report/index.html`` links both scenes' reports and quotes the error tables.
"""

from __future__ import annotations

import html
import logging
from pathlib import Path

from ilt import __version__
from ilt.decompose.stage import decompose, load_operator
from ilt.evaluate.errors import bounce_isf_errors
from ilt.io.atomic import atomic_path
from ilt.io.manifest import MANIFEST, StageError, read_manifest, write_json, write_manifest
from ilt.io.preview import matrix_panel
from ilt.io.staged import staged_directory
from ilt.io.workspace_dirs import Workspace
from ilt.isf.directory import load_isf
from ilt.report.page import STYLE, fig5_matrices, write_report
from ilt.sim import ILLUMINATIONS, make_scene
from ilt.transport.operators import cancellation_operator
from ilt.workspace.simulate import write_simulation

log = logging.getLogger(__name__)

#: beams per scene of the exact-ISF experiment: full demo and --quick
DEMO_BEAMS = {"m": (128, 64), "box": (432, 108)}
#: beams per scene scanned by the simulated rig: full demo and --quick
RIG_BEAMS = {"m": (64, 16), "box": (48, 12)}
PAPER_TRACER_BOUNCES = 7

#: the simulated rig of configs/sim.toml, per scene (the plan matches the rendered scene)
RIG_TEMPLATE = """\
# ilt demo: the emulated rig looking at the simulated "{scene}" scene ({beams} beams).
[ptu]
port = "emulator"
settle = 0.0
emulator_speed = 20000

[laser]
control = "ptu-aux"

[camera]
backend = "sim"
model = "ilt SimSensor"
scene = "{scene}"
px_per_beam = {px_per_beam}
rows = 32
spot = 0.1
radiance_scale = 1.0e8

[bracket]
shutter = ["1/15", "1/30", "1/60", "1/125", "1/250", "1/500", "1/1000", "1/2000", "1/4000", "1/8000"]
aperture = 1.2
extra = [{{ shutter = "1/8000", aperture = 16 }}]

[plan]
{plan}

[photos]
sim = ["flashlight", "room", "projector"]

[decompose]
bounces = 8
"""


def rig_config(scene: str, beams: int) -> str:
    """The demo's rig TOML for a scene: a line across the M, a grid over the box."""
    if scene == "m":
        plan = f'kind = "line"\npan = [-20.0, 20.0]\ntilt = 0.0\ncount = {beams}'
    else:
        n = round((beams / 3) ** 0.5)
        plan = f'kind = "grid"\npan = [-10.0, 10.0]\ntilt = [-8.0, 6.0]\nshape = [{3 * n}, {n}]'
    return RIG_TEMPLATE.format(scene=scene, beams=beams, px_per_beam=16.0, plan=plan)


def run_scene(name: str, out: Path, quick: bool, cache_dir: Path, force: bool) -> dict:
    """The exact-ISF experiment of one scene under ``out`` (Fig. 5 errors and figures)."""
    beams = DEMO_BEAMS[name][1 if quick else 0]
    scene = make_scene(name, beams=beams)
    isf_dir = write_simulation(scene, out / "isf", {"scene": name, "beams": scene.m}, force=force)
    isf = load_isf(isf_dir)
    photos = [isf_dir / "photos" / f"{kind}.exr" for kind in ILLUMINATIONS]
    summaries = decompose(isf, photos, out / "decompose", cache_dir=cache_dir, force=force)
    op, _ = load_operator(isf.T, cache_dir)
    fig5 = matrix_panel(out / "fig5.png", fig5_matrices(isf.T, op))
    truth = scene.bounce_isfs(5)
    T7, _ = scene.isf(max_bounces=PAPER_TRACER_BOUNCES)
    errors = {
        "exact": bounce_isf_errors(op, isf.T, truth),
        f"tracer_{PAPER_TRACER_BOUNCES}_bounces": bounce_isf_errors(cancellation_operator(T7), T7, truth),
    }
    write_json(out / "fig5-errors.json", {"scene": name, "m": scene.m, "errors": errors})
    return {
        "scene": name,
        "m": scene.m,
        "isf": str(isf_dir),
        "fig5": str(fig5),
        "previews": [str(Path(s["output"]) / "preview.png") for s in summaries],
        "errors": errors,
    }


def run_rig(name: str, ws: Workspace, quick: bool, force: bool) -> Path:
    """``ilt run`` on the simulated rig in workspace ``ws``, then its report."""
    from ilt.workspace.pipeline import load_run_config, run_pipeline

    ws.root.mkdir(parents=True, exist_ok=True)
    text = rig_config(name, RIG_BEAMS[name][1 if quick else 0])
    if not ws.config.exists() or ws.config.read_text() != text:
        with atomic_path(ws.config) as tmp:
            tmp.write_text(text)
    run_pipeline(ws, load_run_config(ws.config), force=force)
    return write_report(ws)


#: the stage named by the manifest.json that marks a demo's output directory
DEMO_STAGE = "demo"


def claim_output(out: Path, quick: bool) -> None:
    """Make ``out`` the demo's: it must be absent, empty or an earlier demo's output
    (else StageError, nothing touched); it is then marked by ``out/manifest.json``.

    The mark lists no outputs: the demo's workspaces and stage directories below it
    carry their own manifests, and no stage may replace ``out`` as a whole.
    """
    if out.is_dir() and any(out.iterdir()):
        try:
            manifest = read_manifest(out)
        except StageError:
            manifest = None
        if not isinstance(manifest, dict) or manifest.get("stage") != DEMO_STAGE:
            names = sorted(p.name for p in out.iterdir())
            raise StageError(f"{out} holds files that are not an earlier 'ilt demo' output ({', '.join(names[:5])}"
                             f"{' ...' if len(names) > 5 else ''}); choose an empty or new directory")
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / MANIFEST, {"stage": DEMO_STAGE, "ilt_version": __version__, "parameters": {"quick": quick},
                                "inputs": {}, "outputs": {}})


def run_demo(out: str | Path, quick: bool = False, force: bool = False) -> list[dict]:
    """Both scenes: the simulated rig and the exact experiment; then OUT/report/index.html.

    ``out`` must be absent, empty or an earlier demo's output (:func:`claim_output`).
    """
    out = Path(out)
    claim_output(out, quick)
    results = []
    for name in DEMO_BEAMS:
        log.info("demo: %s scene, simulated rig in %s", name, out / name)
        report = run_rig(name, Workspace(out / name), quick, force)
        result = run_scene(name, out / name / "exact", quick, out / ".cache", force=True)
        results.append({**result, "report": str(report), "workspace": str(out / name)})
    results_page(out / "report", results)
    return results


def results_page(path: Path, results: list[dict]) -> Path:
    """OUT/report/index.html: links to each scene's report and the Fig. 5 tables."""
    with staged_directory(path, force=True) as tmp:
        body = []
        for r in results:
            scene = r["scene"]
            body.append(f"<h2>{scene} scene</h2><p><a href=\"../{scene}/report/index.html\">"
                        f"the simulated rig's report</a> (workspace <code>{scene}/</code>)</p>")
            fig = f"fig5-{scene}.png"
            Path(tmp / fig).write_bytes(Path(r["fig5"]).read_bytes())
            body.append(f'<figure><img src="{fig}" alt="exact T and Cn T, {scene}"><figcaption>exact T of the '
                        f"{html.escape(scene)} scene (m = {r['m']}) and its Cn T (Fig. 5)</figcaption></figure>")
            body.append(f"<pre>{html.escape(error_table(r))}</pre>")
        (tmp / "index.html").write_text(
            f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>ilt demo</title><style>{STYLE}</style>"
            "</head><body><h1>ilt demo</h1>" + "\n".join(body) + "</body></html>\n")
        write_manifest(tmp, "demo-report", {})
    return path / "index.html"


def error_table(result: dict) -> str:
    """The Fig. 5 comparison as text: mean/max squared distance per bounce."""
    lines = [f"{result['scene']} (m = {result['m']}): squared distance of normalised columns, Cn T vs truth"]
    lines.append(f"{'n':>3} {'exact mean':>12} {'exact max':>12} {'7-bounce mean':>14} {'7-bounce max':>13}")
    exact, traced = result["errors"].values()
    for e, t in zip(exact, traced):
        lines.append(f"{e['n']:>3} {e['mean']:>12.3e} {e['max']:>12.3e} {t['mean']:>14.3e} {t['max']:>13.3e}")
    return "\n".join(lines)
