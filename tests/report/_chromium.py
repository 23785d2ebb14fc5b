"""Render an HTML report in headless Chromium: layout facts from the DOM and a screenshot.

No DevTools protocol: a copy of the page gets a script that, once every image has
loaded or failed, writes the page width, each table's width and each image's load
state into a ``<pre id="layout-check">`` element; ``--dump-dom`` returns the DOM after
the script ran.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

WINDOW_WIDTH = 1280  # [px] browser window; the report's page is at most 1100 px wide

_PROBE = """
<script>
window.addEventListener("load", () => {
  const body = document.body, cs = getComputedStyle(body), r = body.getBoundingClientRect();
  const left = r.left + parseFloat(cs.paddingLeft), right = r.right - parseFloat(cs.paddingRight);
  const out = {
    page: {left: left, right: right, width: right - left},
    scrollWidth: document.documentElement.scrollWidth,
    innerWidth: window.innerWidth,
    height: document.documentElement.scrollHeight,
    tables: [...document.querySelectorAll("table")].map(t => {
      const b = t.getBoundingClientRect();
      return {title: (t.previousElementSibling || {}).textContent || "", left: b.left,
              right: b.right, width: b.width, scrollWidth: t.scrollWidth};
    }),
    images: [...document.images].map(i => ({src: i.getAttribute("src"), complete: i.complete,
                                            naturalWidth: i.naturalWidth})),
  };
  const pre = document.createElement("pre");
  pre.id = "layout-check";
  pre.textContent = JSON.stringify(out);
  body.appendChild(pre);
});
</script>
"""


def chromium() -> str | None:
    """Path of a Chromium executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if found := shutil.which(name):
            return found
    return None


def _run(exe: str, *args: str) -> subprocess.CompletedProcess:
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--allow-file-access-from-files", "--virtual-time-budget=10000", *args]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True)


def layout(html_path: Path, exe: str) -> dict:
    """Layout facts of the page (see the module docstring) at `WINDOW_WIDTH`."""
    probe = html_path.with_name(html_path.stem + "_layout_probe.html")
    probe.write_text(html_path.read_text(encoding="utf-8").replace("</body>", _PROBE + "</body>"),
                     encoding="utf-8")  # fmt: skip
    try:
        dom = _run(exe, f"--window-size={WINDOW_WIDTH},1000", "--dump-dom", probe.as_uri()).stdout
    finally:
        probe.unlink()
    m = re.search(r'<pre id="layout-check">(.*?)</pre>', dom, re.S)
    assert m, "the layout probe did not run"
    return json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))


def screenshot(html_path: Path, png: Path, exe: str, height: int) -> Path:
    """Full-page screenshot `WINDOW_WIDTH` × `height` px of the page into `png`."""
    _run(exe, f"--window-size={WINDOW_WIDTH},{height}", f"--screenshot={png}", html_path.as_uri())
    return png
