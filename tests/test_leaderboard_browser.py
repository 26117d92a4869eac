"""The leaderboard page in a real headless browser (Debian's Chromium): it sorts, images load."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from saferace.experiments.benchmark import RunSpec, load_suite, run_benchmark
from saferace.experiments.benchmark_page import leaderboard_html

#: Appended to a copy of the page: once it has loaded, click "agent" (sort ascending) and
#: "score" twice (descending), then write what the table and the images show, and whether
#: the table's last column ends inside the window, into the DOM.
PROBE = """
<script>
window.addEventListener("load", () => {
  const headers = Array.from(document.querySelectorAll("th"));
  const click = (name) => headers.find((h) => h.textContent === name).click();
  const column = (index) => Array.from(document.querySelectorAll("tbody tr"))
    .map((row) => row.cells[index].textContent);
  click("agent");
  const byAgent = column(1);
  click("score"); click("score");
  const byScore = column(1);
  const images = Array.from(document.images).map((i) => i.complete && i.naturalWidth > 0);
  const lastHeader = headers[headers.length - 1].getBoundingClientRect().right;
  const fits = lastHeader <= document.documentElement.clientWidth;
  const out = document.createElement("pre");
  out.id = "probe";
  out.textContent = JSON.stringify({byAgent, byScore, images, fits});
  document.body.appendChild(out);
});
</script>
"""


WINDOW = "1400,1000"  # a laptop's browser window (px)


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    raise AssertionError("no Chromium: `make test-slow` installs it (scripts/install_chromium.sh)")


@pytest.mark.slow
def test_the_page_sorts_and_shows_its_images_in_chromium(tmp_path: Path):
    runs = [RunSpec("lab", "CenterLine", 0, "none"), RunSpec("oval", "RacingLine", 0, "none")]
    entries = [
        run_benchmark(agent, tmp_path / f"{agent}.json", progress=False, runs=runs)
        for agent in ("pure-pursuit", "expert", "weave")
    ]
    page = leaderboard_html(entries, load_suite())
    (tmp_path / "leaderboard.html").write_text(page)
    probe = tmp_path / "probe.html"
    probe.write_text(page.replace("</body>", PROBE + "</body>"))
    browser = [chromium(), "--headless", "--no-sandbox", "--disable-gpu"]
    dom = subprocess.run(
        [*browser, "--virtual-time-budget=5000", f"--window-size={WINDOW}", "--dump-dom",
         probe.as_uri()],
        capture_output=True, text=True, timeout=120, check=True,
    ).stdout  # fmt: skip
    shown = json.loads(re.search(r'<pre id="probe">(.*?)</pre>', dom, re.S).group(1))
    assert shown["byAgent"] == ["expert", "pure-pursuit", "weave"]
    scores = {entry["agent"]: entry["score"] for entry in entries}
    assert shown["byScore"] == sorted(scores, key=scores.get, reverse=True)
    assert shown["images"] == [True, True]  # lab and oval
    assert shown["fits"]  # every column on screen at 1,400 px
    screenshot = tmp_path / "leaderboard.png"
    subprocess.run(
        [*browser, f"--screenshot={screenshot}", f"--window-size={WINDOW}",
         (tmp_path / "leaderboard.html").as_uri()],
        capture_output=True, timeout=120, check=True,
    )  # fmt: skip
    assert screenshot.stat().st_size > 20_000
