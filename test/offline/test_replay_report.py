"""The replay's report folder (OUT/report/): one row per keyframe with its candidates, decisions
and labels, loop images, a self-contained page; the page in a real browser (headless Debian
`chromium`, as CI installs it; skips where it is missing, fails under CI=true); --write-bag's
loop images; the decision log decided again at the run's settings gives the run's loops.

The revisit world (test/bag_fixtures.py) with top_k 3 and any score accepted: 17 keyframes, 7
loops, of which the tiny random network's re-ranking gets 1 true and 6 false.
"""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import cv2
import numpy as np
import pytest
from bag_fixtures import revisit_world, write_rosbag2
from extras import in_ci
from report_pages import REVISIT as CONFIG
from report_pages import check_report
from rosbags.highlevel import AnyReader

from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.offline.report.html.labels import FLAG_NAMES


def load_js(path, call: str):
    """The JSON argument(s) of a data file `call(...)` (index.js, rows-NNNN.js)."""
    text = path.read_text()
    return json.loads("[" + re.fullmatch(rf"{re.escape(call)}\((.*)\);\s*", text, re.S)[1] + "]")


def links(page: str) -> list[str]:
    """The distinct src / href values of the page's tags (not inside its scripts)."""
    found = set()

    class Parser(HTMLParser):
        def handle_starttag(self, tag, attrs):
            found.update(v for k, v in attrs if k in ("src", "href") and v)

    Parser().feed(page)
    return sorted(found)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("report")
    bag = write_rosbag2(tmp / "bag", *revisit_world())
    options = ReplayOptions(progress=False, write_bag=True)
    summary = replay_bag(bag, tmp / "out", options, model=tiny_model, config=CONFIG)
    assert summary.error is None
    return summary, tmp / "out"


def test_one_row_per_keyframe_with_candidates_decisions_and_labels(replayed):
    summary, out = replayed
    report = out / "report"
    (index,) = load_js(report / "index.js", "PAIRVPR.index")
    chunks = [load_js(f, "PAIRVPR.rows") for f in sorted((report / "rows").glob("rows-*.js"))]
    assert [number for number, _ in chunks] == [0]
    rows = chunks[0][1]
    assert index["rows"] == len(rows) == summary.pipeline_counts["keyframes"] == 17
    assert [r["n"] for r in rows] == list(range(17)) and [r["k"] for r in rows] == [*range(17)]
    assert all(r["c"] == [] and r["d"] == [] and "exclusion window" in r["why"] for r in rows[:10])
    flags, names = index["flags"], FLAG_NAMES
    ev = summary.evaluation
    count = {name: sum(1 for f in flags if f & bit) for name, bit in names.items()}
    assert (count["accepted"], count["false"], count["true"]) == (7, 6, 1)
    assert (ev["false_accepted"], ev["true_accepted"]) == (6, 1)
    assert count["missed"] == ev["positives"] - ev["true_accepted"] == 4
    assert count["pose"] == 7  # no camera_info: every accepted loop's pose is refused
    row = rows[12]  # the one true loop: keyframe 12 -> 2, its global best
    assert [d["id"] for d in row["d"]] == [2] and row["d"][0]["a"] == 1
    assert row["d"][0]["why"] == "accepted: score 0.61 >= score_threshold -1e+09"
    assert [c[0] for c in row["c"]] == [2, 5, 4] and index["labels"][12] == "tff"
    candidate = row["c"][0]  # [id, image row, similarity, pair score, rank before, after, map]
    assert candidate[1] == 2 and candidate[4:] == [1, 1, -1]
    assert {len(r["c"]) for r in rows[10:]} == {3}


def test_images_and_page_are_self_contained(replayed):
    summary, out = replayed
    report = out / "report"
    page = (report / "index.html").read_text()
    assert '<table id="keyframes" data-keyframes="17">' in page
    refs = links(page)  # every file the page loads or links to: in the folder, none fetched
    assert refs == ["index.js", "pr_curve.png", "trajectory.png"]
    assert all((report / ref).is_file() for ref in refs)
    assert "http://" not in page and "https://" not in page
    images = sorted((report / "img").rglob("*.jpg"))
    assert len(images) == 17
    loops = sorted((report / "loops").rglob("*.jpg"))
    assert len(loops) == summary.loops == 7
    picture = cv2.imread(str(loops[0]))
    assert picture.shape == (42 + 192, 2 * 192 + 4, 3)  # 32 px squares drawn 192 px high
    assert np.abs(picture[5, 5].astype(int) - [40, 120, 40]).max() <= 12  # accepted (JPEG)
    assert summary.report["keyframes"] == 17 and summary.report["bytes"] > 0
    written = json.loads((out / "summary.json").read_text())
    assert written["report"] == summary.report and written["suggestion"] == summary.suggestion


def test_write_bag_has_one_loop_image_per_accepted_loop(replayed):
    summary, out = replayed
    with AnyReader([out / "bag"]) as reader:
        images = [
            reader.deserialize(raw, c.msgtype)
            for c, _, raw in reader.messages()
            if c.topic == "/loop_closure/image"
        ]
    assert len(images) == summary.loops == 7
    first = images[0]
    assert (first.encoding, first.header.stamp.sec, first.header.frame_id) == ("bgr8", 100, "cam")
    assert (first.height, first.width) == (42 + 240, 2 * 240 + 4)
    bgr = first.data.reshape(first.height, first.width, 3)
    assert bgr[5, 5].tolist() == [40, 120, 40]


def test_the_decision_log_decides_the_run_again(replayed):
    summary, _ = replayed
    run = summary.suggestion["run_decided_again"]
    assert summary.suggestion["mismatches_with_run"] == 0
    assert (run["accepted"], run["true"], run["false"]) == (7, 1, 6)
    # no threshold separates the tiny network's 1 true loop from its 6 false ones
    assert summary.suggestion["reached"] is False


def test_the_page_in_chromium(replayed):
    """No console error, every <img> decodes, one row per keyframe, the false filter's rows."""
    if check_report.chromium() is None:
        reason = "chromium is not installed: apt-get install chromium (.ci/run installs it)"
        if in_ci():
            pytest.fail(f"CI: {reason}", pytrace=False)
        pytest.skip(reason)
    summary, out = replayed
    problems, pages = check_report.check(out)
    assert problems == []
    first, false = pages["first"], pages["false"]  # the page as it opens: all 17 rows on it
    assert (first["state"], first["keyframes"], first["console"]) == ("ready", 17, [])
    assert first["rows"] == [str(k) for k in range(17)]
    assert (first["images"], first["broken"]) == (17 + 7 * 3 + 7, 0)  # queries, candidates, loops
    assert len(false["rows"]) == false["matching"] == summary.evaluation["false_accepted"] == 6
