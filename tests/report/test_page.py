"""`ilt report`: the page loads in a headless browser, every image is decoded and drawn."""

import html as html_lib
import json
import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exr import write_exr
from ilt.io.preview import bounce_panel
from ilt.io.workspace_dirs import Workspace
from ilt.report.page import write_report

CHECK = """<script>
window.addEventListener("load", () => {
  const imgs = [...document.images];
  const bad = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute("src"));
  const p = document.createElement("p");
  p.id = "ilt-check";
  p.textContent = `images=${imgs.length} broken=[${bad.join(",")}]`;
  document.body.appendChild(p);
});
</script></body>"""


def find_chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        if path := shutil.which(name):
            return path
    return None


@pytest.fixture(scope="module")
def report(workspace):  # noqa: F811
    result = CliRunner().invoke(cli, ["report", "-w", str(workspace)])
    assert result.exit_code == 0, result.output
    return workspace / "report" / "index.html"


def _frame(shape=(40, 300)):
    """A smooth (H, W, 3) picture with dark and bright parts, like a flatland frame."""
    y, x = np.indices(shape) / np.array(shape)[:, None, None]
    grey = 1.0 + np.sin(14 * x) * np.cos(3 * y)
    return np.stack([grey, 0.9 * grey, 0.8 * grey], axis=2).astype(np.float32)


@pytest.fixture(scope="module")
def full_resolution_report(tmp_path_factory):
    """A workspace with only decompose/: one photo with full-resolution images at the top
    of its directory (the layout decompose writes with a fine operator), and one with
    only a preview.png (no full-resolution images)."""
    root = tmp_path_factory.mktemp("fullres")
    photo = _frame()
    (root / "photos").mkdir()
    write_exr(root / "photos" / "flash.exr", photo, channels=["R", "G", "B"])
    flash = root / "decompose" / "flash"
    (flash / "samples").mkdir(parents=True)
    factors = {"bounce-1": 0.8, "bounce-2": 1 / 12, "bounce-3": 1 / 40, "bounce-4": 1 / 130, "indirect": 0.2,
               "residual": 1e-3}
    for name, factor in factors.items():
        write_exr(flash / f"{name}.exr", photo * factor, channels=["R", "G", "B"], attributes={"quantity": name})
    write_exr(flash / "coverage.exr", np.ones(photo.shape[:2], np.float32))
    bounce_panel(flash / "preview.png", {"photo": photo[:, :, 0], "bounce 1": 0.8 * photo[:, :, 0],
                                         "bounce 2": photo[:, :, 0] / 12, "indirect": 0.2 * photo[:, :, 0]})
    summary = {
        "input": str(root / "photos" / "flash.exr"),
        "decomposition": {"bounces": 4, "stopped_early": False, "relative_norms": [0.8, 0.08], "noise": None,
                          "negative_share": [], "limits": {"tol": 0.0, "solver": None}, "warnings": []},
        "full_resolution": {"written": True, "degree": 1, "pixels": 12000, "coverage": 1.0, "saturated_pixels": 0},
    }
    (flash / "summary.json").write_text(json.dumps(summary))
    old = root / "decompose" / "old"
    old.mkdir()
    bounce_panel(old / "preview.png", {"photo": photo[::10, ::50, 0], "L1": photo[::10, ::50, 0] / 2})
    (old / "summary.json").write_text(json.dumps({"input": str(root / "photos" / "old.npy"), "decomposition": {
        "bounces": 2, "stopped_early": True, "warnings": ["stopped early"]}}))
    return write_report(Workspace(root))


def test_report_has_every_section(report):
    page = report.read_text()
    for title in ("Capture", "Fig. 4", "Fig. 5", "Fig. 6", "Operator diagnostics", "flashlight", "Is the scene Lambertian?"):
        assert title in page
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert {"spots.png", "fig5.png", "photo-flashlight.png", "lambertian.png"} <= set(srcs)
    assert all((report.parent / s).exists() and "/" not in s for s in srcs)


def _cells(page):
    return [html_lib.unescape(c) for c in re.findall(r"<td>(.*?)</td>", page)]


@pytest.mark.parametrize("which", ["report", "full_resolution_report"])
def test_every_image_is_a_picture_and_every_value_reads(which, request):
    index = request.getfixturevalue(which)
    page = index.read_text()
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert srcs
    for src in srcs:
        picture = cv2.imread(str(index.parent / src))
        assert picture is not None and picture.std() > 20, src
    cells = _cells(page)
    assert cells and not [c for c in cells if re.search(r"\bNone\b|\bTrue\b|\bFalse\b|\[|\{", c)], cells


def test_photos_show_their_preview_and_tables_read(full_resolution_report):
    out = full_resolution_report.parent
    page = html_lib.unescape(full_resolution_report.read_text())
    assert "flash: the photo, its bounce images and the indirect part at the photo's resolution" in page
    assert "old: the photo, its bounce images and the indirect part at the m samples" in page
    for name in ("flash", "old"):
        assert (out / f"photo-{name}.png").read_bytes() == (out.parent / "decompose" / name / "preview.png").read_bytes()
    cells = _cells(page)
    for value in ("—", "none", "no", "yes", "tol: 0, solver: —", "0.8, 0.08"):
        assert value in cells, value
    assert "Full resolution" in page and "stopped early" in page


def _screenshot(browser, page, out, profile):
    subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--allow-file-access-from-files",
         f"--user-data-dir={profile}", "--window-size=1400,5000", f"--screenshot={out}", page.as_uri()],
        capture_output=True, text=True, timeout=120, check=False)
    shot = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert shot is not None, f"chromium wrote no screenshot of {page}"
    return shot


@pytest.mark.parametrize("which", ["report", "full_resolution_report"])
def test_report_figures_show_in_a_headless_chromium_screenshot(which, request, tmp_path):
    """The page with its figures is darker than the page without them by about the dark
    pixels of the figures themselves: they are drawn, and not blank."""
    browser = find_chromium()
    if browser is None:
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")
    index = request.getfixturevalue(which)
    page = index.read_text()
    bare = index.parent / "no-images.html"
    bare.write_text(re.sub(r"<img [^>]*>", "", page))
    with_figures = _screenshot(browser, index, tmp_path / "page.png", tmp_path / "profile")
    without = _screenshot(browser, bare, tmp_path / "bare.png", tmp_path / "profile")
    bare.unlink()
    dark_in_files = sum(int((cv2.imread(str(index.parent / s), cv2.IMREAD_GRAYSCALE) < 64).sum())
                        for s in re.findall(r'<img src="([^"]+)"', page))
    added = int((with_figures < 64).sum()) - int((without < 64).sum())
    # shown at their own size, or scaled down to the page's 1400 pixels
    assert added > 0.4 * dark_in_files > 10_000, (added, dark_in_files)


def test_report_renders_in_headless_chromium(report, tmp_path):
    browser = find_chromium()
    if browser is None:
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")
    probe = report.parent / "check.html"
    probe.write_text(report.read_text().replace("</body>", CHECK))
    out = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
         f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=120, check=False)
    m = re.search(r'id="ilt-check">images=(\d+) broken=\[([^\]]*)\]', out.stdout)
    assert m, f"the page did not finish loading: {out.stderr[-2000:]}"
    assert int(m.group(1)) >= 3 and m.group(2) == "", m.group(0)
