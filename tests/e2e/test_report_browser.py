"""The HTML report in headless Chromium: every image loads, no console message, and a screenshot.

Chromium is Debian's ``chromium`` package (CI installs it); when it is absent or cannot start, the test
skips with the reason. Images are checked in the browser itself: a copy of index.html beside it gets a
small script that records, after the load event, every <img> that did not decode (``naturalWidth`` 0);
``--dump-dom`` then shows the result. The report itself has no scripts, so any console line Chromium
logs for it (``--enable-logging=stderr``: ``CONSOLE``) is an error.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.unit.test_report import make_run, make_scene
from uncertsplat.config import ReportConfig
from uncertsplat.stages import report as stage

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"
_CHECK = """<script>
window.addEventListener("load", function () {
  var bad = [];
  for (var i = 0; i < document.images.length; i++) {
    var im = document.images[i];
    if (!(im.complete && im.naturalWidth > 0)) bad.push(im.getAttribute("src"));
  }
  document.body.setAttribute("data-images", String(document.images.length));
  document.body.setAttribute("data-broken", JSON.stringify(bad));
});
</script>"""


def _chromium() -> str | None:
    for c in ("/usr/bin/chromium", shutil.which("chromium"), shutil.which("chromium-browser")):
        if c and os.path.exists(c):
            return c
    return None


def _run(browser: str, tmp: Path, args: list[str], url: str) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp / 'chromium-profile'}", "--virtual-time-budget=10000"]
    return subprocess.run([browser, *flags, *args, url], capture_output=True, text=True, timeout=120)


def test_report_opens_in_chromium(tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip("chromium is not installed (Debian: apt-get install chromium)")
    try:
        probe = _run(browser, tmp_path, ["--dump-dom"], "data:text/html,<p>ok</p>")
    except (OSError, subprocess.TimeoutExpired) as err:
        pytest.skip(f"chromium cannot start: {err}")
    if probe.returncode != 0 or "ok" not in probe.stdout:
        pytest.skip(f"chromium cannot start (exit {probe.returncode}): {probe.stderr.strip()[-300:]}")

    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    a = make_run(tmp_path / "baseline", "run", names=names, scene=scene, seed=1)
    b = make_run(tmp_path / "pruned", "run", names=names, scene=scene, seed=2, stats=False, prune=True)
    out = tmp_path / "report"
    index = stage.run([a, b], out, ReportConfig())

    html = index.read_text(encoding="utf-8")
    n_img = len(re.findall(r"<img ", html))
    assert n_img >= 8
    check = out / "_check.html"
    check.write_text(html.replace("</body>", _CHECK + "</body>"), encoding="utf-8")
    res = _run(browser, tmp_path, ["--dump-dom"], check.as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    m = re.search(r'data-images="(\d+)"', res.stdout)
    assert m is not None, "the load event did not fire: " + res.stdout[-500:]
    assert int(m.group(1)) == n_img
    broken = json.loads(re.search(r"data-broken=\"([^\"]*)\"", res.stdout).group(1).replace("&quot;", '"'))
    assert broken == [], f"images that did not load: {broken}"
    check.unlink()

    ARTIFACTS.mkdir(exist_ok=True)
    shot = ARTIFACTS / "report.png"
    res = _run(browser, tmp_path, ["--enable-logging=stderr", "--v=0", f"--screenshot={shot}",
                                   "--window-size=1280,2000"], index.as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    console = [line for line in res.stderr.splitlines() if "CONSOLE" in line]
    assert console == [], f"console messages: {console}"
    assert shot.is_file() and shot.stat().st_size > 10_000
