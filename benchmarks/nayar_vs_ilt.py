"""ilt's bounce 1 / indirect beside Nayar et al.'s direct / global, on matte and glossy scenes.

    python benchmarks/nayar_vs_ilt.py [--beams 64] [--patterns 4,8,16]

The projector lights the scene fully (the photo ilt splits with C1 = T1 T^-1 of the
scene's T, m laser beams + 1 photo) and through K stripe patterns shifted by 1/K of a
cycle (what ``ilt separate`` splits, K photos); both against the simulator's truth:
bounce 1, and the indirect part (photo - bounce 1). Relative L2 errors over the samples.
"""

from __future__ import annotations

import argparse

import numpy as np

from ilt.separate.nayar import direct_global
from ilt.sim.gloss import glossy_scene
from ilt.sim.lighting import PROJECTOR_PERIOD_DEG
from ilt.sim.scene import make_scene
from ilt.transport.operators import bounce_images, cancellation_operator


def _error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def compare(lit, patterns: list[int], period: float = PROJECTOR_PERIOD_DEG) -> dict:
    """Errors of ilt's and Nayar's split of the fully lit projector photo of ``lit`` (Scene or GlossyScene)."""
    photo, bounces = lit.photo("projector", n_bounces=60, pattern="full")
    direct, indirect = bounces[0], photo - bounces[0]
    T, _ = lit.isf()
    first = bounce_images(cancellation_operator(T), photo, 1).bounces[0]
    out = {"ilt": (_error(first, direct), _error(photo - first, indirect))}
    for k in patterns:
        stack = np.stack([lit.photo("projector", n_bounces=1, period_deg=period, phase_deg=2 * period * i / k)[0]
                          for i in range(k)])
        d, g = direct_global(stack)
        out[f"nayar {k}"] = (_error(d, direct), _error(g, indirect))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--beams", type=int, default=64)
    parser.add_argument("--patterns", default="4,8,16")
    parser.add_argument("--period", type=float, default=PROJECTOR_PERIOD_DEG,
                        help="stripe width in degrees (a cycle is twice it)")
    args = parser.parse_args()
    patterns = [int(k) for k in args.patterns.split(",")]
    print(f"bounce 1 (direct) / indirect (global) relative errors, m = {args.beams}, stripes {args.period:g} deg; "
          "photos needed: "
          f"ilt {args.beams} beams + 1, Nayar K")
    print("| scene | gloss | ilt (C1 = T1 T^-1) | " + " | ".join(f"Nayar K = {k}" for k in patterns) + " |")
    print("|---|---|---|" + "---|" * len(patterns))
    for name in ("m", "textured", "occluded"):
        scene = make_scene(name, args.beams)
        for gloss in (0.0, 0.2, 0.4):
            if gloss and name == "textured":
                continue
            lit = scene if gloss == 0 else glossy_scene(scene, gloss)
            row = compare(lit, patterns, args.period)
            cells = [f"{a:.3g} / {b:.3g}" for a, b in row.values()]
            print(f"| {name} | {gloss:g} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
