"""Bad-input matrix, the replay's report (OUT/report/): a keyframe without an image and
candidates of a prior map (no image of theirs here), a candidate never scored, a replay without
ground truth. The report says what is missing and the page still opens; the report folder's own
cases (a file, other files, a full disk) are in test_bad_input_replay.py."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from bag_fixtures import revisit_world, synthetic_images, write_rosbag2
from report_pages import REVISIT as CONFIG
from report_pages import check_report

from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.offline.replay.options import ReplayOptions, ReplaySummary
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html import PageInputs, ReportWriter, write_page

WHO = ("robot", "s1")


def rows_of(report: Path) -> list[dict]:
    text = (report / "rows" / "rows-0000.js").read_text()
    return json.loads(text.removeprefix("PAIRVPR.rows(0,").removesuffix(");\n"))


def test_keyframe_without_image_and_prior_map_candidates(tmp_path):
    live = Candidate(0, 0.0, "cam", 0.9, 1, 2.5, robot="robot", session="s1")
    prior = Candidate(7, 5.0, "cam", 0.8, 2, 3.1, robot="r2", session="old", prior=0)
    unscored = Candidate(8, 6.0, "cam", 0.7, 3, robot="r2", session="old", prior=0)
    loops = [
        LoopRecord(1, 40.0, "cam", 7, 5.0, "cam", 3.1, 0.8, 2, 1, accepted=True,
                   match_robot="r2", match_session="old"),
        LoopRecord(1, 40.0, "cam", 0, 0.0, "cam", 2.5, 0.9, 1, 1, reason="score below threshold"),
    ]  # fmt: skip
    outcomes = [
        FrameOutcome(0.0, keyframe_id=0),  # the first keyframe: nothing to search
        FrameOutcome(40.0, keyframe_id=1, loop=loops[0], loops=loops,
                     candidates=[live, prior, unscored], timings_ms={"search": 1.0}),
    ]  # fmt: skip
    writer, log = ReportWriter(tmp_path / "report", CONFIG, WHO), DecisionLog()
    for number, (outcome, rgb) in enumerate(
        zip(outcomes, [synthetic_images(1)[0], None], strict=True)
    ):
        assert log.add(outcome) == number
        writer.add(number, outcome, rgb)
    page_s = write_page(writer, log, PageInputs(ReplaySummary("bag", "/cam", None).to_dict()))
    assert page_s >= 0.0
    first, second = rows_of(tmp_path / "report")
    assert "i" not in first and second["i"] is False  # no image of keyframe 1
    # [id, image row, similarity, pair score, rank before, rank after, map]: the prior map's
    # keyframes have no image here (-1); one was never scored (None), so has no rank after
    assert [c[:2] for c in second["c"]] == [[0, 0], [7, -1], [8, -1]]
    assert [c[3:6] for c in second["c"]] == [[2.5, 1, 1], [3.1, 2, 1], [None, 3, None]]
    assert [(d["id"], d["a"]) for d in second["d"]] == [(7, 1), (0, 0)]
    picture = cv2.imread(str(tmp_path / "report" / second["d"][0]["img"]))
    assert picture.shape[0] == 42 + 192  # drawn, both sides as grey "no image" panels
    grey = np.abs(picture[42 + 40 :, :, :].astype(int) - 90).max(axis=2) <= 12
    assert grey.mean() > 0.8
    assert not list((tmp_path / "report" / "img").rglob("1.jpg"))
    if check_report.chromium() is not None:  # the page shows both rows, every <img> decodes
        page = check_report.open_page(tmp_path / "report" / "index.html")
        assert (page["state"], page["rows"], page["broken"]) == ("ready", ["0", "1"], 0)
        assert page["console"] == []


def test_replay_without_ground_truth(tmp_path, tiny_model):
    bag = write_rosbag2(tmp_path / "bag", *revisit_world())
    options = ReplayOptions(progress=False, gt_topic="none", pose_topic="none")
    summary = replay_bag(bag, tmp_path / "out", options, model=tiny_model, config=CONFIG)
    assert summary.error is None and summary.evaluation is None
    assert summary.suggestion is None and not (tmp_path / "out/suggested_params.yaml").exists()
    report = tmp_path / "out" / "report"
    text = (report / "index.js").read_text()
    index = json.loads(text.removeprefix("PAIRVPR.index(").removesuffix(");\n"))
    assert [f & 1 for f in index["flags"]] == [0] * 10 + [1] * 7  # accepted: known
    assert all(f & ~(1 | 8 | 16) == 0 for f in index["flags"])  # true, false, missed: not
    assert set("".join(index["labels"])) == {"-"}
    page = (report / "index.html").read_text()
    assert "none: no precision, recall or labels (pass --gt-topic)" in page
    assert "No ground truth, so no curve." in page
