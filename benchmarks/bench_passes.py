"""`ilt run` with refine passes against uniform scans of as many beams, on the emulated rig (issue 21).

    python benchmarks/bench_passes.py [--base 16] [--passes 2] [--beams 4] [--keep DIR]

The emulated rig of configs/sim.toml (pan-tilt unit on a pseudo-terminal, the simulated
camera writing DNG brackets with photon and read noise, the M scene) scans:

- **refined**: a line of ``--base`` beams, then ``--passes`` passes of ``ilt refine``
  adding ``--beams`` each, captured where refine aimed them (``[refine]`` in the config);
- **uniform**: lines of ``--base`` beams and of each of ``--uniform`` (default: base +
  passes x beams, the same rig time, and 2 x base),
  with ``px_per_beam`` scaled so every scan sees the same frame and ``spot`` (in beam
  spacings) so every scan has the same laser spot.

Each is ``ilt run`` end to end (capture -> merge -> centroids -> build-isf -> photos ->
decompose). Errors: relative L2 of the full-resolution bounces 1-3 (decompose's
bounce-N.exr, the green grid merge makes) of each photo against the renderer's exact
bounces of the scan's own scene (in the units of its merged photo), over the pixels
every scan covers. Prints a markdown
table, the mean per scan, each run's time, the **equivalent uniform beams** of the refined
scan (the uniform beam count with its error, interpolated in log error between the
uniform scans) and the landing error of refine's beams.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from ilt.evaluate.end_to_end import green_grid, rendered_scene
from ilt.io.exr import read_exr
from ilt.io.workspace_dirs import Workspace
from ilt.workspace.pipeline import load_run_config, run_pipeline

ROOT = Path(__file__).resolve().parents[1]
PHOTOS = ("flashlight", "room", "projector")


def config(beams: int, px_per_beam: float, refine: str = "", spot: float = 0.1, scene: str = "m") -> str:
    """configs/sim.toml for ``beams`` beams of ``scene`` (the box: a grid of 3 n x n, as ilt demo's)."""
    text = (ROOT / "configs" / "sim.toml").read_text()
    text = re.sub(r'scene = "\w+"', f'scene = "{scene}"', text)
    if scene == "box":
        n = round((beams / 3) ** 0.5)
        plan = f'kind = "grid"\nunits = "degrees"\npan = [-10.0, 10.0]\ntilt = [-8.0, 6.0]\nshape = [{3 * n}, {n}]\n'
        text = re.sub(r"^\[plan\].*?(?=^\[|^# |\Z)", "[plan]\n" + plan + "\n", text, flags=re.DOTALL | re.MULTILINE)
    text = re.sub(r"count = \d+", f"count = {beams}", text)
    text = re.sub(r"px_per_beam = [0-9.]+", f"px_per_beam = {px_per_beam!r}", text)
    text = re.sub(r"spot = [0-9.]+", f"spot = {spot!r}", text)
    return text + refine


def run(root: Path, name: str, text: str, added: np.ndarray | None = None) -> tuple[Workspace, float]:
    """``ilt run`` of ``text`` in ``root/name``; ``added``: (k, 2) pan/tilt written as a
    done refine pass first (a random scan's beams, shot as a pass's are)."""
    ws = Workspace(root / name)
    ws.root.mkdir(parents=True, exist_ok=True)
    (ws.root / "config.toml").write_text(text)
    if added is not None and not (ws.root / "passes" / "pass-1" / "manifest.json").exists():
        d = ws.root / "passes" / "pass-1"
        d.mkdir(parents=True, exist_ok=True)
        with open(d / "refine.csv", "w") as f:
            f.write("x,y,pan,tilt,gain\n" + "".join(f"0,0,{float(p)!r},{float(t)!r},0\n" for p, t in added))
        (d / "manifest.json").write_text('{"stage": "random"}\n')
    t0 = time.monotonic()
    run_pipeline(ws, load_run_config(ws.root / "config.toml"))
    return ws, time.monotonic() - t0


def errors(ws: Workspace, mask: np.ndarray) -> np.ndarray:
    """(photos, 3) relative errors of bounces 1-3 over ``mask``."""
    cfg = load_run_config(ws.root / "config.toml")
    scene, sensor = rendered_scene(cfg.rig)
    out = np.empty((len(PHOTOS), 3))
    for p, kind in enumerate(PHOTOS):
        photo, bounces = scene.photo(kind, n_bounces=3)
        # the rig's units: the merged photo against the rendered one (radiance scale, gain)
        measured = read_exr(ws.stage_dir("photos") / f"{kind}.exr")[0][..., 0].astype(np.float64)
        truth = green_grid(bounces, sensor) * measured[mask].sum() / green_grid(photo, sensor)[mask].sum()
        for n in range(3):
            est = read_exr(ws.stage_dir("decompose") / kind / f"bounce-{n + 1}.exr")[0][..., 0].astype(np.float64)
            out[p, n] = np.linalg.norm((est - truth[n])[mask]) / np.linalg.norm(truth[n][mask])
    return out


def coverage(ws: Workspace) -> np.ndarray:
    return read_exr(ws.stage_dir("decompose") / "room" / "coverage.exr")[0][..., 0] > 0


def equivalent(uniform: list[tuple[int, float]], error: float) -> str:
    """The uniform beam count with ``error``, interpolated in log error between the two
    uniform scans around it (errors falling with beams); a bound when outside them."""
    for (m0, e0), (m1, e1) in itertools.pairwise(uniform):
        if e1 <= error <= e0 and e0 > e1:
            return f"{m0 + (m1 - m0) * np.log(e0 / error) / np.log(e0 / e1):.1f}"
    return f"more than {uniform[-1][0]}" if error < uniform[-1][1] else f"fewer than {uniform[0][0]}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="m", help="m, occluded, textured (a line of beams) or box (a grid)")
    parser.add_argument("--base", type=int, default=16)
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--beams", type=int, default=4)
    parser.add_argument("--uniform", help="uniform beam counts besides --base (default: the refined count, 2 x base)")
    parser.add_argument("--random", type=int, default=0,
                        help="also this many scans of base + passes x beams beams at random angles in the plan's range")
    parser.add_argument("--keep", help="keep the workspaces here")
    args = parser.parse_args()
    total = args.base + args.passes * args.beams
    # configs/sim.toml's frame: 32 beams at 16 px; the box: ilt demo's 108 at 16 px
    px = 16.0 * 32 / args.base if args.scene != "box" else 16.0 * (108 / args.base) ** 0.5
    side = (lambda c: (c / args.base) ** 0.5) if args.scene == "box" else (lambda c: c / args.base)
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(args.keep or scratch)
        counts = sorted({int(c) for c in args.uniform.split(",")} if args.uniform else {total, 2 * args.base})
        refined = f"refined {args.base} + {args.passes} x {args.beams}"
        scans = {f"uniform {args.base}": config(args.base, px, scene=args.scene),
                 refined: config(args.base, px, f"\n[refine]\npasses = {args.passes}\nbeams = {args.beams}\n",
                                 scene=args.scene)}
        scans.update({f"uniform {c}": config(c, px / side(c), spot=0.1 * side(c), scene=args.scene) for c in counts})
        done = {name: run(root, f"{args.scene}-" + name.replace(" ", "-").replace("+", "p"), text)
                for name, text in scans.items()}
        rng = np.random.default_rng(0)
        for d in range(args.random):   # flatland: pan uniform over the line's range, tilt 0
            pans = rng.uniform(-20.0, 20.0, args.passes * args.beams)
            done[f"random {d}"] = run(root, f"{args.scene}-random-{d}", config(
                args.base, px, f"\n[refine]\npasses = 1\nbeams = {args.passes * args.beams}\n", scene=args.scene),
                np.column_stack([pans, np.zeros_like(pans)]))
        masks = [coverage(ws) for ws, _ in done.values()]
        shapes = {m.shape for m in masks}
        if len(shapes) != 1:
            raise SystemExit(f"the scans' frames differ in shape: {shapes}")
        mask = np.logical_and.reduce(masks)
        print(f"pixels every scan covers: {int(mask.sum())} of {mask.size}\n")
        print("| scan | beams | " + " | ".join(f"{k} b{n}" for k in PHOTOS for n in (1, 2, 3)) +
              " | mean | run s |\n|---|---|" + "---|" * (3 * len(PHOTOS) + 2))
        means = {}
        for name, (ws, seconds) in done.items():
            e = errors(ws, mask)
            means[name] = float(e.mean())
            beams = len(json.loads((ws.stage_dir("capture") / "manifest.json").read_text())["beams"])
            print(f"| {name} | {beams} | " + " | ".join(f"{v:.4f}" for v in e.ravel()) +
                  f" | {means[name]:.4f} | {seconds:.1f} |")
        uniform = sorted((int(n.split()[1]), e) for n, e in means.items() if n.startswith("uniform"))
        randoms = [e for n, e in means.items() if n.startswith("random")]
        if randoms:
            print(f"\nrandom (median of {len(randoms)}): {np.median(randoms):.4f}; refined / random "
                  f"{means[refined] / np.median(randoms):.3f}")
        print(f"\nrefined / uniform {args.base}: {means[refined] / means[f'uniform {args.base}']:.3f}; "
              f"refined / uniform {total}: {means[refined] / means.get(f'uniform {total}', np.nan):.3f}")
        print(f"equivalent uniform beams of the refined {total}: {equivalent(uniform, means[refined])}")
        landing = json.loads((done[refined][0].root / "passes" / "landing.json").read_text())
        for p in landing["passes"]:
            print(f"pass {p['pass']}: {p['found']} of {p['beams']} new beams found, landing median "
                  f"{p['median_px']} px, max {p['max_px']} px")


if __name__ == "__main__":
    main()
