"""``ilt demo``: the paper's experiments on built-in simulated scenes.

For the "M" scene (paper Fig. 3-6) and the box (Fig. 7-9): simulate the ISF and
photos, decompose every photo, draw T and Cn T (Fig. 5) and each photo's bounce
images (Fig. 6), and measure the Fig. 5 errors against the exact truth, both with
exact transport and with the paper's forward tracer truncated at 7 bounces.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ilt.decompose import decompose, load_operator
from ilt.evaluate import bounce_isf_errors
from ilt.isf import load_isf
from ilt.manifest import write_json
from ilt.preview import matrix_panel
from ilt.sim import ILLUMINATIONS, make_scene
from ilt.simulate import write_simulation
from ilt.transport import bounce_images, cancellation_operator

log = logging.getLogger(__name__)

#: beams per scene: full demo and --quick
DEMO_BEAMS = {"m": (128, 64), "box": (432, 108)}
PAPER_TRACER_BOUNCES = 7


def fig5_matrices(T, operator, n_max: int = 4) -> dict:
    """T, C1 T ... Cn T and the indirect part T - C1 T, as in the paper's Fig. 5."""
    bounces = bounce_images(operator, T, n_bounces=n_max).bounces
    panels = {"T": T}
    panels.update({f"C{n} T": b for n, b in enumerate(bounces, start=1)})
    panels["T - C1 T"] = T - bounces[0]
    return panels


def run_scene(name: str, out: Path, quick: bool, cache_dir: Path, force: bool) -> dict:
    """Simulate, decompose and measure one scene under ``out/<name>``."""
    beams = DEMO_BEAMS[name][1 if quick else 0]
    scene = make_scene(name, beams=beams)
    base = out / name
    isf_dir = write_simulation(scene, base / "isf", {"scene": name, "beams": scene.m}, force=force)
    isf = load_isf(isf_dir)
    photos = [isf_dir / "photos" / f"{kind}.exr" for kind in ILLUMINATIONS]
    summaries = decompose(isf, photos, base / "decompose", cache_dir=cache_dir, force=force)
    op, _ = load_operator(isf.T, cache_dir)
    fig5 = matrix_panel(base / "fig5.png", fig5_matrices(isf.T, op))
    truth = scene.bounce_isfs(5)
    T7, _ = scene.isf(max_bounces=PAPER_TRACER_BOUNCES)
    errors = {
        "exact": bounce_isf_errors(op, isf.T, truth),
        f"tracer_{PAPER_TRACER_BOUNCES}_bounces": bounce_isf_errors(cancellation_operator(T7), T7, truth),
    }
    write_json(base / "fig5-errors.json", {"scene": name, "m": scene.m, "errors": errors})
    return {
        "scene": name,
        "m": scene.m,
        "isf": str(isf_dir),
        "fig5": str(fig5),
        "previews": [str(Path(s["output"]) / "preview.png") for s in summaries],
        "errors": errors,
    }


def run_demo(out: str | Path, quick: bool = False, force: bool = False) -> list[dict]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [run_scene(name, out, quick, out / ".cache", force) for name in DEMO_BEAMS]


def error_table(result: dict) -> str:
    """The Fig. 5 comparison as text: mean/max squared distance per bounce."""
    lines = [f"{result['scene']} (m = {result['m']}): squared distance of normalised columns, Cn T vs truth"]
    lines.append(f"{'n':>3} {'exact mean':>12} {'exact max':>12} {'7-bounce mean':>14} {'7-bounce max':>13}")
    exact, traced = result["errors"].values()
    for e, t in zip(exact, traced):
        lines.append(f"{e['n']:>3} {e['mean']:>12.3e} {e['max']:>12.3e} {t['mean']:>14.3e} {t['max']:>13.3e}")
    return "\n".join(lines)
