"""The reciprocity verdict (ilt.transport.reciprocity) against gloss and noise on the glossy simulator.

    python benchmarks/lambertian_verdicts.py [--beams 32] [--seeds 20]

For each flatland scene (m, textured, occluded), a glossy share g of every patch's
reflection (ilt.sim.gloss) and photon-like noise of relative sigma s on every entry of T
(plus a floor of 1e-4 of T's peak), prints the robust residual and the verdict (the most
common over the seeds, with its share), and for the matte scenes the false-alarm rate
("not lambertian" on a matte T) over the seeds. Also bounce errors of the paper's
operator on the glossy scenes against the simulator's truth.
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np

from ilt.sim.gloss import glossy_scene
from ilt.sim.scene import make_scene
from ilt.transport.operators import bounce_images, cancellation_operator
from ilt.transport.reciprocity import reciprocity_check

GLOSS = (0.0, 0.05, 0.1, 0.2, 0.4)
NOISE = (0.0, 0.01, 0.03, 0.1)


def verdicts(T: np.ndarray, noise: float, seeds: int) -> tuple[float, Counter]:
    if noise == 0:
        r = reciprocity_check(T)
        return r.residual, Counter([r.verdict])
    residuals, counts = [], Counter()
    for seed in range(seeds):
        var = (noise * T) ** 2 + (1e-4 * T.max()) ** 2
        noisy = T + np.random.default_rng(seed).normal(0, 1, T.shape) * np.sqrt(var)
        r = reciprocity_check(noisy, var)
        residuals.append(r.residual)
        counts[r.verdict] += 1
    return float(np.median(residuals)), counts


def bounce_errors(glossy, n: int = 3) -> list[float]:
    """Relative errors of bounces 1..n of the flashlight photo split by C1 = T1 T^-1 of the glossy T."""
    T, _ = glossy.isf()
    photo, truth = glossy.photo("flashlight", 40)
    bounces = bounce_images(cancellation_operator(T), photo, n).bounces
    return [float(np.linalg.norm(bounces[k] - truth[k]) / np.linalg.norm(truth[k])) for k in range(n)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args()
    print(f"robust residual (log units) / verdict, m = {args.beams}, noise: median of {args.seeds} draws")
    print("| scene | gloss | " + " | ".join(f"noise {s:g}" for s in NOISE) + " |")
    print("|---|---|" + "---|" * len(NOISE))
    for name in ("m", "textured", "occluded"):
        scene = make_scene(name, args.beams)
        for g in GLOSS:
            T, _ = glossy_scene(scene, g).isf()
            cells = []
            for s in NOISE:
                residual, counts = verdicts(T, s, args.seeds)
                verdict, count = counts.most_common(1)[0]
                share = "" if s == 0 else f" {count}/{sum(counts.values())}"
                alarm = f", false alarms {counts['not lambertian']}/{sum(counts.values())}" if g == 0 and s else ""
                cells.append(f"{residual:.3f} {verdict}{share}{alarm}")
            print(f"| {name} | {g:g} | " + " | ".join(cells) + " |")
    print()
    print("bounce 1 / 2 / 3 errors of the flashlight photo with C1 = T1 T^-1 of the glossy T (M)")
    scene = make_scene("m", args.beams)
    for g in GLOSS:
        errors = bounce_errors(glossy_scene(scene, g))
        print(f"  gloss {g:g}: " + " / ".join(f"{e:.3g}" for e in errors))


if __name__ == "__main__":
    main()
