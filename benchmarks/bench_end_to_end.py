"""What the simulated rig costs: bounce errors of `ilt run` against noise-free frames (issue 7).

    python benchmarks/bench_end_to_end.py [-o DIR] [--quick] [--scenes m,box]

For each scene, the rig config of `ilt demo` (or its --quick size): `ilt run` on the
simulated rig (DNG brackets -> merge -> centroids -> build-isf -> photos -> decompose),
and the same stages on the renderer's noise-free frames of the same beams and photos
(:mod:`ilt.evaluate.end_to_end`). Prints, per photo and bounce 1-4, the relative error of each
against the renderer's truth and their ratio rig / ideal, as a markdown table
(docs/accuracy.md, "End to end").
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from ilt.evaluate.end_to_end import compare, ideal_workspace
from ilt.io.workspace_dirs import Workspace
from ilt.workspace.demo import RIG_BEAMS, rig_config
from ilt.workspace.pipeline import load_run_config, run_pipeline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", help="keep the workspaces here (default: a temporary directory)")
    parser.add_argument("--quick", action="store_true", help="the demo's --quick beam counts")
    parser.add_argument("--scenes", default="m,box")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(args.output or scratch)
        print("| scene | m | photo | bounce | rig | ideal | rig / ideal |\n|---|---|---|---|---|---|---|")
        for scene in args.scenes.split(","):
            beams = RIG_BEAMS[scene][1 if args.quick else 0]
            ws = Workspace(root / scene)
            ws.root.mkdir(parents=True, exist_ok=True)
            ws.config.write_text(rig_config(scene, beams))
            cfg = load_run_config(ws.config)
            run_pipeline(ws, cfg)
            ideal_workspace(cfg.rig, cfg.photo_kinds, root / f"{scene}-ideal", workers=None)
            for kind, f in compare(ws.root, root / f"{scene}-ideal", cfg.rig, cfg.photo_kinds).items():
                for n, (r, i, q) in enumerate(zip(f["rig"], f["ideal"], f["ratio"]), start=1):
                    print(f"| {scene} | {beams} | {kind} | {n} | {r:.4f} | {i:.4f} | {q:.3f} |")


if __name__ == "__main__":
    main()
