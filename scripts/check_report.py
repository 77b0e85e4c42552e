"""Open a replay's report (OUT/report/index.html) in headless Chromium, as a person would from
disk, and check it: no console error, every <img> of the shown rows decodes, one row per keyframe
(all pages), and the "false" filter shows as many rows as the summary's false loops. Prints the
load times. Used by CI on `make demo`'s report and by test/offline/test_report_browser.py.

    python scripts/check_report.py demo_out/replay            # the replay's --out folder
    python scripts/check_report.py demo_out/replay --screenshot docs/demo_report.png

Needs Debian's `chromium` (apt-get install chromium). Exit status 0 when every check passes.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from html.parser import HTMLParser
from pathlib import Path

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--disable-extensions", "--enable-logging=stderr", "--v=0")  # fmt: skip
FALSE_FLAG = 2  # offline/report/html/labels.py


def chromium() -> str | None:
    """The Chromium executable, None when there is none."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


class _Page(HTMLParser):
    """The parts of a dumped DOM the checks read."""

    def __init__(self) -> None:
        super().__init__()
        self.body: dict[str, str] = {}
        self.table: dict[str, str] = {}
        self.rows: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if tag == "body":
            self.body = a
        elif tag == "table" and a.get("id") == "keyframes":
            self.table = a
        elif tag == "tr" and "data-keyframe" in a:
            self.rows.append(a["data-keyframe"])


def open_page(index: Path, fragment: str = "", budget_ms: int = 20000) -> dict:
    """Load `index` (+ `#fragment`) in headless Chromium until its script says it is done ->
    {state, images, broken, rows (data-keyframe of each row shown), keyframes, matching,
    ready_ms (the page's own time to the rows shown, images decoded), wall_s (Chromium's whole
    run), console (every console line: errors, failed loads)}."""
    exe = chromium()
    if exe is None:
        raise FileNotFoundError("chromium is not installed: apt-get install chromium")
    url = index.resolve().as_uri() + (f"#{fragment}" if fragment else "")
    with tempfile.TemporaryDirectory(prefix="pairvpr-chromium-") as profile:
        start = time.perf_counter()
        done = subprocess.run(
            [exe, *FLAGS, f"--user-data-dir={profile}", f"--virtual-time-budget={budget_ms}",
             "--dump-dom", url],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        wall = time.perf_counter() - start
    page = _Page()
    page.feed(done.stdout)
    console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
    b = page.body
    return {
        "state": b.get("data-state", "none"), "images": int(b.get("data-images", -1)),
        "broken": int(b.get("data-broken", -1)), "ready_ms": int(b.get("data-ready-ms", -1)),
        "rows": page.rows, "keyframes": int(page.table.get("data-keyframes", -1)),
        "matching": int(page.table.get("data-matching", -1)), "wall_s": round(wall, 2),
        "console": console, "exit": done.returncode,
    }  # fmt: skip


def screenshot(index: Path, path: Path, size: str = "1400,1800", fragment: str = "") -> None:
    """A PNG of the page as a browser window of `size` shows it."""
    exe = chromium()
    url = index.resolve().as_uri() + (f"#{fragment}" if fragment else "")
    with tempfile.TemporaryDirectory(prefix="pairvpr-chromium-") as profile:
        subprocess.run(
            [exe, *FLAGS, f"--user-data-dir={profile}", "--hide-scrollbars",
             f"--window-size={size}", "--virtual-time-budget=20000",
             f"--screenshot={path.resolve()}", url],
            capture_output=True, timeout=120, check=True,
        )  # fmt: skip


def index_data(report: Path) -> dict:
    """The report's index.js (every row's flags)."""
    text = (report / "index.js").read_text()
    return json.loads(re.fullmatch(r"PAIRVPR\.index\((.*)\);\s*", text, re.S)[1])


def check(out: Path) -> tuple[list[str], dict[str, dict]]:
    """(every problem of the report of the replay folder `out`, empty: all good; the pages
    opened: "first" as it opens, "all" rows, "false" loops); prints the figures."""
    report, problems = out / "report", []
    summary = json.loads((out / "summary.json").read_text())
    keyframes = summary["pipeline_counts"]["keyframes"]
    false_loops = (summary.get("evaluation") or {}).get("false_accepted", 0)
    first = open_page(report / "index.html")
    every = open_page(report / "index.html", "filter=all&page=all")
    false = open_page(report / "index.html", "filter=false&page=all")
    flags = index_data(report)["flags"]
    print(f"report {report}: {keyframes} keyframes, {false_loops} false loops, "
          f"{summary['report']['bytes'] / 1e6:.1f} MB, written in "
          f"{summary['report']['seconds']:.2f} s (replay {summary['seconds']:.1f} s)")  # fmt: skip
    for name, page in (("first page", first), ("all rows", every), ("false loops", false)):
        print(f"  {name}: {len(page['rows'])} rows, {page['images']} images, ready in "
              f"{page['ready_ms']} ms (Chromium's whole run {page['wall_s']} s)")  # fmt: skip
        if page["state"] != "ready":
            problems.append(f"{name}: the page's state is {page['state']!r}, not 'ready'")
        if page["broken"] != 0 or page["images"] <= 0:
            problems.append(f"{name}: {page['broken']} of {page['images']} images do not decode")
        problems += [f"{name}: console: {line}" for line in page["console"]]
    if every["keyframes"] != keyframes or len(every["rows"]) != keyframes:
        problems.append(f"{len(every['rows'])} rows shown, data-keyframes "
                        f"{every['keyframes']}, but {keyframes} keyframes")  # fmt: skip
    if len(set(every["rows"])) != len(every["rows"]):
        problems.append("two rows have the same data-keyframe")
    flagged = sum(1 for f in flags if f & FALSE_FLAG)
    if not len(false["rows"]) == false["matching"] == flagged == false_loops:
        problems.append(f"the false filter shows {len(false['rows'])} rows ({flagged} flagged) "
                        f"but the summary has {false_loops} false loops")  # fmt: skip
    return problems, {"first": first, "all": every, "false": false}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="the replay's --out folder (holds report/)")
    p.add_argument("--screenshot", type=Path, help="also write a PNG of the report's page")
    args = p.parse_args(argv)
    if chromium() is None:
        print("error: chromium is not installed: apt-get install chromium", file=sys.stderr)
        return 2
    problems, _ = check(args.out)
    if args.screenshot is not None:
        screenshot(args.out / "report" / "index.html", args.screenshot)
        print(f"screenshot: {args.screenshot}")
    for problem in problems:
        print(f"error: {problem}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
