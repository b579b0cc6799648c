"""Per-pixel accuracy of the full-resolution bounce images (ilt/isf/fine.py, ilt/decompose/fullres.py) against exact truth.

    python benchmarks/fullres_accuracy.py [--quick] [--json PATH] [--scratch DIR] [--keep]
                                          [--max-render-s 360] [--scenes m,box]

Every case renders noise-free camera frames with ``ilt simulate SCENE --frames`` (beam
frames, the flashlight / room / projector photos and their exact per-pixel n-bounce
frames), then runs the pipeline as a user would::

    ilt -q centroids DIR/hdr -o SPOTS
    ilt -q build-isf DIR/hdr SPOTS -o ISF [--fine-degree D]
    ilt -q decompose --isf ISF DIR/photos/<kind>.exr ... -o OUT --no-cache

and compares OUT/<kind>/bounce-<n>.exr (n = 1..4) and indirect.exr with the truth
(indirect = bounces 2..8 of the truth): the relative L2 error ``||est - truth|| / ||truth||``
over the covered pixels (coverage.exr > 0). Tables (markdown):

1. Sweep: the "M" scene at m = 48, 96, 192, 384, 768 and the box at m = 48, 108, 192, 432,
   768, default --fine-degree (1), each photo. A trend table says, per scene, photo and
   bounce, whether the error falls at every step of m and the ratio largest-m / smallest-m.
   Frame sizes: M (flatland, 32 rows) px_per_beam = max(8, 768 / m), so the frames are
   785 px wide at m = 48 and 96, 1553 at 192, 3089 at 384 (6161 at 768); box px_per_beam
   16 (m <= 108), 12 (192), 10 (432), 8 (768): ~160 to ~300 px square. Not below 8 on the
   M: its frames are one row of spots extruded over 32 rows, and a --max-cell-radius of 2
   spot spacings (build-isf's default until issue 21) left the cells shorter than the strip (at
   px_per_beam 4, m = 192: 16 of 32 rows, coverage 0.49): the cells catch all of each
   spot but only half of its indirect light, T's indirect part comes out halved and the
   errors jump tenfold, at the sample level too (b1 0.19, b2 0.28 for the room photo;
   --max-cell-radius 40 brings them back to 0.011 and 0.023). The laser footprint (--spot, in beam
   spacings) grows where px_per_beam shrinks so that its image stays as wide as at the
   default size (sigma >= 0.6 px on the M, ~1 px on the box): a sub-pixel spot is flagged
   ('elongated') by ilt centroids and its beam dropped, which would measure the centroid
   finder rather than the fine operator. With 3 sigma or more of margin to the cell edge
   the spot's light stays in its own cell (< 0.1% spills). The table prints the m kept by
   build-isf (flagged beams are still dropped as in real use, and counted).
   A size whose render time, extrapolated from the CPU times of the two sizes before it (a
   power law in m, its exponent + 0.5 since it rises with m; CPU time, so that other load
   on the machine does not skip a size), would exceed --max-render-s (default 6 min;
   or whose memory would exceed ~80% of the available RAM) is skipped and flagged in the
   table. Measured on 2 cores: the M at m = 768 renders in ~470 s (13 GB; skipped by
   default), the box at 768 in ~200 s (5 GB).
2. Error against storage at m = 192 (both scenes): --fine-degree 0, 1, 2 and the cheap
   "share" method (each cell's sample-level bounce share times the photo,
   ``bounce_n(p) = photo(p) L_n[i] / L[i]`` for p in cell i: it needs only cells.exr, no
   fine/), with the bytes each stores in ISF/fine/ and that as a fraction of the beam
   frames' bytes (the HDR EXR files on disk; the raw float32 size is printed too).
3. The textured M (m = 96, 192) and the occluded M (m = 96) at the default degree.
4. Stripe pattern check (projector photo, every case above): bounce 2 of a striped
   projector is light that has been scattered once more by a Lambertian surface, so it
   must be smooth: the stripes must all be in bounce 1. Two high-pass measures, each as a
   fraction of the photo's, ``S(img) = hf(img) / hf(photo)``, L2 over the covered pixels:
   S_cell: ``hf(img) = ||img - cellmean(img)||``, ``cellmean`` the image's mean over each of
   the ISF's cells (cells.exr): the variation inside the cells. S_smooth:
   ``hf(img) = ||img - G * img||``, G a Gaussian of sigma = 2 beam spacings (2 px_per_beam)
   over the covered pixels (normalised convolution): it also sees steps between cells,
   to which S_cell is blind (degree 0 is flat in every cell: S_cell = 0 by construction).
   The photo's high-pass energy is nearly all stripe edges (the period is ~160 px on the
   M's 785 px frame), so S(est bounce 2) far above S(true bounce 2) means the estimate
   carries the stripes (the share method's bounce 2 is its cell's share times the photo,
   so its S is about the bounce-2 share, ~0.2); S(est) near S(true) or below means it
   does not (S(true) is the smooth light's own curvature and its kinks at folds and
   edges, not zero).

``--quick``: m = 48 and 96 (M) / 108 (box) only, the comparison at the largest of those
(m = 96 / 108) instead of 192, the textured M at m = 96 only and the occluded M at 96.
``--json PATH`` writes every number. Scratch data goes to a temporary directory under
/tmp (removed at the end unless --keep); each case's frames are deleted once evaluated.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from ilt.io.exr import read_exr
from ilt.isf.directory import load_isf

KINDS = ("flashlight", "room", "projector")
BOUNCES = (1, 2, 3, 4)
COLUMNS = ["b1", "b2", "b3", "b4", "indirect"]
SIZES = {"m": [48, 96, 192, 384, 768], "box": [48, 108, 192, 432, 768]}
QUICK_SIZES = {"m": [48, 96], "box": [48, 108]}
COMPARE_M = {"m": 192, "box": 192}
BOX_PX = {48: 16, 108: 16, 192: 12, 432: 10, 768: 8}
FLATLAND = ("m", "textured", "occluded")


def frame_parameters(scene: str, m: int) -> tuple[float, float]:
    """(px_per_beam, spot) of a case: see the module docstring."""
    if scene in FLATLAND:
        px = max(8.0, 768.0 / m)
        return px, max(0.05, 0.6 / px)                     # image sigma spot * px >= 0.6 px
    px = float(BOX_PX.get(m, max(8, min(16, round(16 * (108 / m) ** 0.25)))))
    return px, 0.05 * 16.0 / px                            # ~1 px, as at px_per_beam 16


def run(cmd: list[str], log: Path) -> tuple[float, float, float]:
    """Run one ilt command; (wall seconds, peak RSS in MiB, CPU seconds). Raises with its stderr on failure."""
    start = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "ilt", "-q", *cmd], stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    if proc.returncode:
        raise RuntimeError(f"ilt {' '.join(cmd)} failed ({proc.returncode}):\n{log.read_text()[-3000:]}")
    return wall, usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime


def tree_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) if Path(path).exists() else 0


def available_mib() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 1024.0
    return math.inf


def rel(est: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.linalg.norm((est - truth)[mask]) / max(np.linalg.norm(truth[mask]), 1e-300))


def smooth_residual(img: np.ndarray, mask: np.ndarray, sigma: float) -> float:
    """||img - G * img|| over mask, G a Gaussian of sigma px over the mask's pixels only."""
    w = mask.astype(np.float64)
    weight = np.maximum(gaussian_filter(w, sigma, mode="constant"), 1e-12)
    blurred = gaussian_filter(img * w, sigma, mode="constant") / weight
    return float(np.linalg.norm((img - blurred)[mask]))


def within_cell(img: np.ndarray, labels: np.ndarray, m: int) -> float:
    """||img - cellmean(img)|| over the pixels inside cells (labels >= 0)."""
    inside = labels >= 0
    lab, v = labels[inside], img[inside].astype(np.float64)
    area = np.maximum(np.bincount(lab, minlength=m), 1)
    mean = np.bincount(lab, v, m) / area
    return float(np.linalg.norm(v - mean[lab]))


class Case:
    """One rendered scene at one m: its frames, spots, ISFs and decompositions under root."""

    def __init__(self, root: Path, scene: str, m: int, max_elongation: float | None = None):
        self.scene, self.m, self.max_elongation = scene, m, max_elongation
        self.px, self.spot = frame_parameters(scene, m)
        self.dir = root / f"{scene}-{m}"
        self.sim = self.dir / "sim"
        self.timing: dict[str, float] = {}

    def render(self) -> dict:
        self.dir.mkdir(parents=True)
        wall, rss, cpu = run(["simulate", self.scene, "--frames", "--beams", str(self.m),
                              "--px-per-beam", f"{self.px:g}", "--spot", f"{self.spot:g}", "-o", str(self.sim)],
                             self.dir / "simulate.log")
        self.timing["render_s"], self.timing["render_cpu_s"], self.render_rss = wall, cpu, rss
        self.shape = tuple(np.load(self.sim / "truth" / "photos" / "room-bounces.npy", mmap_mode="r").shape[1:])
        self.hdr_bytes = tree_bytes(self.sim / "hdr") - (self.sim / "hdr" / "manifest.json").stat().st_size
        extra = [] if self.max_elongation is None else ["--max-elongation", f"{self.max_elongation:g}"]
        wall, *_ = run(["centroids", str(self.sim / "hdr"), "-o", str(self.dir / "spots"), *extra],
                      self.dir / "centroids.log")
        self.timing["centroids_s"] = wall
        return {"render_s": self.timing["render_s"], "render_rss_mib": rss}

    def build(self, degree: int) -> Path:
        isf = self.dir / f"isf-{degree}"
        wall, *_ = run(["build-isf", str(self.sim / "hdr"), str(self.dir / "spots"), "-o", str(isf),
                       "--fine-degree", str(degree)], self.dir / f"build-{degree}.log")
        self.timing[f"build_{degree}_s"] = wall
        return isf

    def decompose(self, isf: Path, tag: str) -> Path:
        out = self.dir / f"dec-{tag}"
        photos = [str(self.sim / "photos" / f"{k}.exr") for k in KINDS]
        wall, *_ = run(["decompose", "--isf", str(isf), *photos, "-o", str(out), "--no-cache"],
                      self.dir / f"decompose-{tag}.log")
        self.timing[f"decompose_{tag}_s"] = wall
        return out

    def truth(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        photo = read_exr(self.sim / "photos" / f"{kind}.exr")[0][..., 0].astype(np.float64)
        return photo, np.load(self.sim / "truth" / "photos" / f"{kind}-bounces.npy").astype(np.float64)

    def evaluate(self, isf: Path, dec: Path, share: bool = False) -> dict:
        """{kind: {"errors": [b1..b4, indirect], "stripe": ...}} of the fine operator's images
        (or of the share method's, from the same decomposition, when share)."""
        loaded = load_isf(isf)
        labels, m = np.asarray(loaded.cells), loaded.m
        out = {}
        for kind in KINDS:
            photo, truth = self.truth(kind)
            d = dec / kind
            cov = read_exr(d / "coverage.exr")[0][..., 0] > 0
            if share:
                bounces = np.load(d / "bounces.npy").reshape(-1, m)
                L = bounces.sum(axis=0) + np.load(d / "residual.npy").reshape(m)
                ratio = np.where(L != 0, bounces / np.where(L != 0, L, 1.0), 0.0)      # (N, m)
                inside = labels >= 0
                est = {}
                for n in BOUNCES:
                    img = np.zeros_like(photo)
                    img[inside] = photo[inside] * ratio[n - 1][labels[inside]]
                    est[n] = img
                est["indirect"] = np.where(inside, photo - est[1], 0.0)
            else:
                est = {n: read_exr(d / f"bounce-{n}.exr")[0][..., 0].astype(np.float64) for n in BOUNCES}
                est["indirect"] = read_exr(d / "indirect.exr")[0][..., 0].astype(np.float64)
            errors = [rel(est[n], truth[n - 1], cov) for n in BOUNCES]
            errors.append(rel(est["indirect"], truth[1:].sum(axis=0), cov))
            hf_photo = within_cell(photo, labels, m)
            sigma = 2.0 * self.px
            sm_photo = smooth_residual(photo, cov, sigma)
            indirect = np.linalg.norm(truth[1:].sum(axis=0)[cov]) / np.linalg.norm(photo[cov])
            out[kind] = {"errors": errors, "coverage": float(cov.mean()), "indirect_share": float(indirect),
                         "stripe": {"cell": {"est_b2": within_cell(est[2], labels, m) / hf_photo,
                                             "true_b2": within_cell(truth[1], labels, m) / hf_photo},
                                    "smooth": {"est_b2": smooth_residual(est[2], cov, sigma) / sm_photo,
                                               "true_b2": smooth_residual(truth[1], cov, sigma) / sm_photo},
                                    "smooth_sigma_px": sigma}}
        return out

    def isf_info(self, isf: Path) -> dict:
        manifest = json.loads((isf / "manifest.json").read_text())
        fine = isf / "fine"
        fine_manifest = json.loads((fine / "manifest.json").read_text()) if (fine / "manifest.json").exists() else {}
        coefficients = fine / "coefficients.npy"
        return {"m_kept": int(manifest["m"]), "fine_bytes": tree_bytes(fine),
                "coefficient_bytes": coefficients.stat().st_size if coefficients.exists() else 0,
                "cells_bytes": (isf / "cells.exr").stat().st_size,
                "flat_cells": fine_manifest.get("flat_cells")}

    def describe(self) -> dict:
        return {"scene": self.scene, "m": self.m, "px_per_beam": self.px, "spot": self.spot,
                "frame": list(self.shape), "hdr_bytes": self.hdr_bytes,
                "hdr_raw_float32_bytes": int(np.prod(self.shape)) * self.m * 4, "timing_s": dict(self.timing),
                "render_rss_mib": self.render_rss}

    def clean(self, keep: bool) -> None:
        if not keep:
            shutil.rmtree(self.dir, ignore_errors=True)


def fmt(v: float) -> str:
    return f"{v:.4f}"


def sweep_row(c: dict, kind: str, variant: dict) -> str:
    r = variant["results"][kind]
    h, w = c["frame"]
    return (f"| {c['scene']} | {c['m']} | {variant['isf']['m_kept']} | {h}x{w} | {c['px_per_beam']:g} "
            f"| {c['spot']:.3g} | {kind} | {r['coverage']:.3f} | " + " | ".join(fmt(e) for e in r["errors"]) + " |")


SWEEP_HEAD = ("| scene | m | m kept | frame HxW | px/beam | spot | photo | covered | b1 | b2 | b3 | b4 | indirect |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="m = 48 and 96 (M) / 108 (box) only")
    parser.add_argument("--json", type=Path, help="write every number here")
    parser.add_argument("--scratch", type=Path, help="scratch parent directory (default /tmp)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch directory")
    parser.add_argument("--scenes", default="m,box", help="sweep scenes (m, box)")
    parser.add_argument("--max-render-s", type=float, default=360.0,
                        help="skip a size whose extrapolated render time exceeds this")
    parser.add_argument("--max-elongation", type=float,
                        help="pass to ilt centroids (default: its own, 2): spots stretched more are dropped")
    args = parser.parse_args()

    scratch = Path(tempfile.mkdtemp(prefix="ilt-fullres-", dir=args.scratch or "/tmp"))
    sizes = QUICK_SIZES if args.quick else SIZES
    compare_m = {s: (max(QUICK_SIZES[s]) if args.quick else COMPARE_M[s]) for s in SIZES}
    report = {"quick": args.quick, "sweep": [], "skipped": [], "compare": [], "other": [], "host_cpus": os.cpu_count()}
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    def default_case(scene: str, m: int, compare: bool = False) -> dict:
        case = Case(scratch, scene, m, args.max_elongation)
        progress(f"{scene} m={m}: render (px/beam {case.px:g}, spot {case.spot:.3g})")
        case.render()
        progress(f"{scene} m={m}: frame {case.shape[0]}x{case.shape[1]}, render {case.timing['render_s']:.1f} s, "
                 f"{case.render_rss:.0f} MiB; pipeline")
        isf = case.build(1)
        dec = case.decompose(isf, "1")
        variants = {"degree 1": {"isf": case.isf_info(isf), "results": case.evaluate(isf, dec)}}
        if compare:
            for degree in (0, 2):
                progress(f"{scene} m={m}: degree {degree}")
                other = case.build(degree)
                variants[f"degree {degree}"] = {"isf": case.isf_info(other),
                                                "results": case.evaluate(other, case.decompose(other, str(degree)))}
            info = dict(case.isf_info(isf), fine_bytes=0, coefficient_bytes=0, flat_cells=None)
            variants["share"] = {"isf": info, "results": case.evaluate(isf, dec, share=True)}
        entry = dict(case.describe(), variants=variants)
        case.clean(args.keep)
        return entry

    try:
        for scene in args.scenes.split(","):
            history: list[tuple[int, float, float, float]] = []     # (m, render CPU s, wall s, peak MiB)
            for m in sizes[scene]:
                if len(history) >= 2:
                    # from CPU time, not wall time: other work on the machine must not skip a size
                    (m0, t_a, _, r_a), (m1, t_b, w_b, r_b) = history[-2:]
                    p_t = min(max(math.log(max(t_b, 1e-3) / max(t_a, 1e-3)) / math.log(m1 / m0), 1.0), 3.0)
                    p_r = min(max(math.log(r_b / r_a) / math.log(m1 / m0), 0.5), 3.0)
                    # the exponent rises with m (the M: 2.0, 2.2, then 2.8 from 384 to 768), hence + 0.5;
                    # wall = CPU / the last render's parallelism (>= 1: as on an idle machine)
                    est_t = t_b * (m / m1) ** (p_t + 0.5) / max(1.0, t_b / max(w_b, 1e-3))
                    est_r = r_b * (m / m1) ** p_r
                    if est_t > args.max_render_s or est_r > 0.8 * available_mib():
                        why = (f"estimated render {est_t:.0f} s on an idle machine (limit {args.max_render_s:.0f} s), "
                               f"{est_r:.0f} MiB (available {available_mib():.0f} MiB)")
                        progress(f"{scene} m={m}: skipped: {why}")
                        report["skipped"].append({"scene": scene, "m": m, "why": why})
                        continue
                entry = default_case(scene, m, compare=(m == compare_m[scene]))
                t = entry["timing_s"]
                history.append((m, t["render_cpu_s"], t["render_s"], entry["render_rss_mib"]))
                report["sweep"].append(entry)
                if "degree 0" in entry["variants"]:
                    report["compare"].append(entry)
        for scene, m in ([("textured", 96), ("occluded", 96)] if args.quick
                         else [("textured", 96), ("textured", 192), ("occluded", 96)]):
            report["other"].append(default_case(scene, m))
    finally:
        if not args.keep:
            shutil.rmtree(scratch, ignore_errors=True)
        else:
            progress(f"kept {scratch}")
    report["total_s"] = time.perf_counter() - t0
    print_tables(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
        print(f"\nJSON: {args.json}")


def print_tables(report: dict) -> None:
    print("## 1. Per-pixel relative error ||est - truth|| / ||truth|| over covered pixels, --fine-degree 1\n")
    print(SWEEP_HEAD)
    for c in report["sweep"]:
        for kind in KINDS:
            print(sweep_row(c, kind, c["variants"]["degree 1"]))
    for s in report["skipped"]:
        print(f"| {s['scene']} | {s['m']} | skipped: {s['why']} |")

    print("\n### Does the error fall as m grows? (errors at increasing m; 'falls' = lower at every step)\n")
    print("| scene | photo | bounce | m | errors | falls | last / first |\n|---|---|---|---|---|---|---|")
    for scene in SIZES:
        cases = [c for c in report["sweep"] if c["scene"] == scene]
        if len(cases) < 2:
            continue
        ms = ",".join(str(c["m"]) for c in cases)
        for kind in KINDS:
            for b, name in enumerate(COLUMNS):
                e = [c["variants"]["degree 1"]["results"][kind]["errors"][b] for c in cases]
                falls = all(y < x for x, y in zip(e, e[1:]))
                print(f"| {scene} | {kind} | {name} | {ms} | " + " ".join(f"{v:.4f}" for v in e)
                      + f" | {'yes' if falls else 'no'} | {e[-1] / e[0]:.2f} |")

    print("\n### Sizes and times\n")
    print("| scene | m | m kept | frame HxW | px/beam | spot | HDR MB | render s | render CPU s | render MiB "
          "| centroids s | build s | decompose s | flat cells |\n" + "|---" * 14 + "|")
    for c in report["sweep"] + report["other"]:
        t, info = c["timing_s"], c["variants"]["degree 1"]["isf"]
        print(f"| {c['scene']} | {c['m']} | {info['m_kept']} | {c['frame'][0]}x{c['frame'][1]} | {c['px_per_beam']:g} "
              f"| {c['spot']:.3g} | {c['hdr_bytes'] / 1e6:.1f} | {t['render_s']:.1f} | {t['render_cpu_s']:.1f} "
              f"| {c['render_rss_mib']:.0f} "
              f"| {t['centroids_s']:.1f} | {t['build_1_s']:.1f} | {t['decompose_1_s']:.1f} | {info['flat_cells']} |")

    print("\n## 2. Error against storage (ISF/fine/ bytes; fraction of the HDR beam frames' EXR bytes)\n")
    print("| scene | m | variant | fine/ bytes | / HDR EXR | / HDR float32 | photo | b1 | b2 | b3 | b4 | indirect "
          "| S_smooth(b2) est (true) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in report["compare"]:
        for name in ("share", "degree 0", "degree 1", "degree 2"):
            v = c["variants"][name]
            size = v["isf"]["fine_bytes"]
            for kind in KINDS:
                r = v["results"][kind]
                print(f"| {c['scene']} | {c['m']} | {name} | {size} | {size / c['hdr_bytes']:.2%} "
                      f"| {size / c['hdr_raw_float32_bytes']:.2%} | {kind} | "
                      + " | ".join(fmt(e) for e in r["errors"])
                      + f" | {r['stripe']['smooth']['est_b2']:.4f} ({r['stripe']['smooth']['true_b2']:.4f}) |")
        print(f"| {c['scene']} | {c['m']} | (HDR frames: {c['hdr_bytes']} bytes EXR, "
              f"{c['hdr_raw_float32_bytes']} float32; cells.exr {c['variants']['share']['isf']['cells_bytes']} "
              "bytes, needed by every variant) |")

    print("\n## 3. Textured and occluded M, --fine-degree 1\n")
    print(SWEEP_HEAD)
    for c in report["other"]:
        for kind in KINDS:
            print(sweep_row(c, kind, c["variants"]["degree 1"]))

    print("\n## 4. Stripe pattern check (projector photo): S(img) = hf(img) / hf(photo); "
          "S_cell: hf = ||img - cellmean(img)||, S_smooth: hf = ||img - Gauss(2 beam spacings) * img||\n")
    print("| scene | m | variant | S_cell est b2 | S_cell true b2 | est / true | S_smooth est b2 | S_smooth true b2 "
          "| est / true |\n|---|---|---|---|---|---|---|---|---|")
    for c in report["sweep"] + report["other"]:
        names = ["share", "degree 0", "degree 1", "degree 2"] if "share" in c["variants"] else ["degree 1"]
        for name in names:
            s = c["variants"][name]["results"]["projector"]["stripe"]
            a, b = s["cell"], s["smooth"]
            print(f"| {c['scene']} | {c['m']} | {name} | {a['est_b2']:.4f} | {a['true_b2']:.4f} "
                  f"| {a['est_b2'] / a['true_b2']:.2f} | {b['est_b2']:.4f} | {b['true_b2']:.4f} "
                  f"| {b['est_b2'] / b['true_b2']:.2f} |")
    print(f"\nTotal {report['total_s']:.0f} s on {report['host_cpus']} CPUs.")


if __name__ == "__main__":
    main()
