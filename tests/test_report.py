"""`ilt report`: the page loads in a headless browser and every image is decoded."""

import re
import shutil
import subprocess

import pytest
from click.testing import CliRunner
from test_run import workspace  # noqa: F401  (the small simulated workspace, built once)

from ilt.cli import cli

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


def test_report_has_every_section(report):
    page = report.read_text()
    for title in ("Capture", "Fig. 4", "Fig. 5", "Fig. 6", "Operator diagnostics", "flashlight"):
        assert title in page
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert {"spots.png", "fig5.png", "photo-flashlight.png"} <= set(srcs)
    assert all((report.parent / s).exists() and "/" not in s for s in srcs)


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
