"""``ilt report``: one self-contained HTML page for a workspace (docs/workspace.md).

``WORKSPACE/report/index.html`` and the PNGs it shows, linked relatively, so the
directory can be copied or served anywhere:

- the scene with every spot found (paper Fig. 4): ``spots/overlay.png``;
- T, Cn T for n = 1..4 and the indirect part T - C1 T (Fig. 5), drawn from ``isf/``;
- each photo with its bounce images (Fig. 6, 9): ``decompose/<photo>/preview.png``,
  drawn by decompose at the photo's resolution where it wrote full-resolution images;
- the diagnostics of the operators and of each decomposition, with their warnings;
- the capture's statistics (beams, frames, exposures skipped, time) from its log.

Sections whose stage has not run are left out with a note.
"""

from __future__ import annotations

import html
import json
import os
import shutil
from pathlib import Path

import numpy as np

from ilt.capture.log import read_log
from ilt.io.manifest import LOG_NAME, MANIFEST, read_manifest, write_manifest
from ilt.io.staged import staged_directory
from ilt.io.workspace_dirs import LANDING_CSV, Workspace

FIG5_BOUNCES = 4


def fig5_matrices(T: np.ndarray, operator, n_max: int = FIG5_BOUNCES) -> dict:
    """T, C1 T ... Cn T and the indirect part T - C1 T, as in the paper's Fig. 5."""
    from ilt.transport.operators import bounce_images

    bounces = bounce_images(operator, T, n_bounces=n_max).bounces
    panels = {"T": T}
    panels.update({f"C{n} T": b for n, b in enumerate(bounces, start=1)})
    panels["T - C1 T"] = T - bounces[0]
    return panels


def capture_statistics(capture_dir: str | os.PathLike) -> dict | None:
    """Beams, frames, exposures skipped and scan time from a capture's manifest and log."""
    capture_dir = Path(capture_dir)
    if not (capture_dir / LOG_NAME).exists():
        return None
    records = read_log(capture_dir / LOG_NAME)
    done = [r for r in records if r["event"] == "beam_done"]
    manifest = read_manifest(capture_dir) if (capture_dir / MANIFEST).exists() else {}
    return {
        "beams": len(manifest.get("beams", [])) or None,
        "beams_shot": len(done),
        "frames": sum(r["frames"] for r in done),
        "exposures_skipped": sum(r["skipped"] for r in done),
        "scan_seconds": round(sum(r["seconds"] for r in done), 1),
        "sessions": sum(1 for r in records if r["event"] in ("start", "resume")),
        "aborts": [r["reason"] for r in records if r["event"] == "abort"],
        "layout": manifest.get("layout"),
        "camera": manifest.get("camera", {}).get("model"),
        "complete": bool(manifest),
    }


def _landing(path: Path) -> str:
    """Each beam a refine pass added: the pixel refine aimed at, the spot found, the
    distance (full-resolution pixels), from ``passes/landing.csv`` (ilt run)."""
    import csv

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    head = ("pass", "beam", "target_x", "target_y", "spot_x", "spot_y", "error_px", "flags")
    cells = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(_number(r.get(k, ''))))}</td>" for k in head) + "</tr>"
                    for r in rows)
    return (f"<p>{len(rows)} beams added by refine passes; the error is the pointing map's "
            "(docs/refine.md)</p><table><tr>" + "".join(f"<th>{k}</th>" for k in head) + "</tr>" + cells + "</table>")


def _number(text: str):
    try:
        return float(text)
    except ValueError:
        return text


def _table(rows: dict) -> str:
    cells = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>"
                    for k, v in rows.items())
    return f"<table>{cells}</table>"


def _fmt(v) -> str:
    """A value as a person reads it: "—" for None, yes / no, "none" for an empty list,
    "key: value" pairs for a dict, numbers to 4 (in a list 3) significant digits."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) or "none"
    if isinstance(v, (list, tuple)):
        return ", ".join(f"{x:.3g}" if isinstance(x, float) else _fmt(x) for x in v) or "none"
    return str(v)


def _warnings(items: list[str]) -> str:
    if not items:
        return '<p class="ok">no warnings</p>'
    return "<ul class=\"warn\">" + "".join(f"<li>{html.escape(w)}</li>" for w in items) + "</ul>"


def _lambertian(isf_dir: Path, tmp: Path) -> str:
    """The reciprocity verdict on T (isf/lambertian.json) and its per-beam map."""
    from ilt.isf.lambertian import LAMBERTIAN_PNG, read_lambertian

    verdict = read_lambertian(isf_dir)
    body = "<h3>Is the scene Lambertian? (reciprocity of T)</h3>"
    if verdict is None:
        return body + '<p class="missing">no lambertian.json (an ISF built before the check)</p>'
    body += _table({k: verdict.get(k) for k in ("verdict", "reciprocity_residual", "noise_floor", "excess",
                                                 "tolerance", "pairs", "beams")})
    if verdict.get("verdict") == "not lambertian":
        body += _warnings([verdict.get("reason", "")])
    if (isf_dir / LAMBERTIAN_PNG).exists():
        shutil.copyfile(isf_dir / LAMBERTIAN_PNG, tmp / "lambertian.png")
        body += _figure("lambertian.png", "each beam's rms asymmetry log T_ij - log T_ji off the fitted "
                                          "diagonal scaling (log units): where the scene is least Lambertian")
    return body


def _figure(src: str, caption: str) -> str:
    return (f'<figure><img src="{html.escape(src)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


STYLE = """body{font-family:sans-serif;max-width:1400px;margin:1em auto;padding:0 1em;color:#222}
img{max-width:100%;border:1px solid #ccc}figure{margin:1em 0}figcaption{color:#555;font-size:90%}
table{border-collapse:collapse;margin:.5em 0}th,td{border:1px solid #ddd;padding:2px 8px;text-align:left}
th{background:#f4f4f4;font-weight:normal}.warn li{color:#a40}.ok{color:#070}.missing{color:#888}"""


def write_report(workspace: Workspace, out: str | os.PathLike | None = None, force: bool = True) -> Path:
    """Write ``out`` (default WORKSPACE/report) with index.html; returns its path.

    ``out`` is replaced only when it is absent, empty or an earlier report holding no
    file of anyone else's (:func:`ilt.io.staged.staged_directory`).
    """
    from ilt.decompose.stage import default_cache_dir, load_operator
    from ilt.io.preview import matrix_panel
    from ilt.isf.directory import load_isf

    ws = workspace
    out = Path(out) if out else ws.report
    spots, isf_dir, dec_dir = ws.stage_dir("centroids"), ws.stage_dir("build-isf"), ws.stage_dir("decompose")
    sections = []
    with staged_directory(out, force=force) as tmp:
        stats = capture_statistics(ws.stage_dir("capture"))
        sections.append("<h2>Capture</h2>" + (_table(stats) if stats else '<p class="missing">no capture</p>'))

        if (ws.passes / LANDING_CSV).is_file():
            sections.append("<h2>Refine passes: where the new beams landed</h2>" + _landing(ws.passes / LANDING_CSV))

        body = "<h2>Scene and spots (Fig. 4)</h2>"
        if (spots / "overlay.png").exists():
            shutil.copyfile(spots / "overlay.png", tmp / "spots.png")
            m = read_manifest(spots)
            body += _figure("spots.png", f"sum of the beam frames with every spot found ({_fmt(m.get('clean'))} "
                                         f"clean of {_fmt(m.get('m'))}; flags {_fmt(m.get('flag_counts'))})")
        else:
            body += '<p class="missing">no spots (run ilt centroids)</p>'
        sections.append(body)

        body = "<h2>Impulse scatter matrix and its bounces (Fig. 5)</h2>"
        if (isf_dir / MANIFEST).exists():
            isf = load_isf(isf_dir)
            op, op_diag = load_operator(isf.T, default_cache_dir(), regularise=False)
            matrix_panel(tmp / "fig5.png", fig5_matrices(isf.T, op))
            body += _figure("fig5.png", f"T ({isf.m} x {isf.m}), Cn T for n = 1..{FIG5_BOUNCES} and the "
                                        "indirect part T - C1 T, each in decades below its max")
            body += "<h3>Operator diagnostics</h3>" + _table(
                {k: v for k, v in op_diag.items() if k not in ("warnings", "fingerprint", "condition_warning")})
            body += _warnings(op_diag["warnings"])
            body += _lambertian(isf_dir, tmp)
        else:
            body += '<p class="missing">no ISF (run ilt build-isf)</p>'
        sections.append(body)

        body = "<h2>Photos and their bounce images (Fig. 6)</h2>"
        photos = sorted(p for p in dec_dir.glob("*/summary.json")) if dec_dir.is_dir() else []
        for summary_path in photos:
            name = summary_path.parent.name
            summary = json.loads(summary_path.read_text())
            body += f"<h3>{html.escape(name)}</h3>"
            full = summary.get("full_resolution", {}).get("written", False)
            if (summary_path.parent / "preview.png").exists():
                shutil.copyfile(summary_path.parent / "preview.png", tmp / f"photo-{name}.png")
                body += _figure(f"photo-{name}.png", f"{name}: the photo, its bounce images and the indirect part "
                                + ("at the photo's resolution" if full else "at the m samples")
                                + ", on one grey scale in photo units; a panel shown brighter says by how much "
                                  "in its title (x10: ten times)")
            else:
                body += '<p class="missing">no preview.png</p>'
            diag = summary["decomposition"]
            body += _table({k: v for k, v in diag.items() if k != "warnings"}) + _warnings(diag["warnings"])
            if "full_resolution" in summary:
                body += "<h4>Full resolution</h4>" + _table(summary["full_resolution"])
        if not photos:
            body += '<p class="missing">no decomposed photos (run ilt decompose)</p>'
        sections.append(body)

        title = f"ilt report: {ws.root.resolve().name}"
        page = (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
                "<p>Seitz, Matsushita &amp; Kutulakos, <i>A Theory of Inverse Light Transport</i> "
                "(ICCV 2005), on this workspace.</p>" + "\n".join(sections) + "</body></html>\n")
        (tmp / "index.html").write_text(page)
        write_manifest(tmp, "report", {})  # marks it as a report: only a report may replace it
    return out / "index.html"
