"""The replay under map_growth places: a represented keyframe (not stored, `query_id` -1) is
still a query of the evaluation, labelled by its stamp (offline/replay/drive.py, run.py,
report/loop_truth.py); tiny random network, exact repeats with depth for metric poses."""

from __future__ import annotations

import numpy as np
from bag_fixtures import textured
from exact_match import EXACT_MATCH
from tqdm import tqdm

from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.offline.bags.reader import BagFrame
from pair_vpr_ros.offline.replay.drive import ReplayRun, drive
from pair_vpr_ros.offline.replay.options import ReplaySummary
from pair_vpr_ros.offline.replay.run import _keyframes
from pair_vpr_ros.offline.report.loop_truth import evaluate_loops
from pair_vpr_ros.types import PoseTrack

H, W = 120, 160
CAMERA = CameraModel(W, H, 100.0, 100.0, 79.5, 59.5)
DEPTH = np.full((H, W), 4.0, np.float32)
ROUTE = [0, 1, 2, 3, 0, 1]  # frames 4 and 5 revisit places 0 and 1


def test_represented_queries_are_labelled_by_stamp(tiny_model):
    config = DetectorConfig(**{**EXACT_MATCH, "map_growth": "places"})
    pipe = LoopClosurePipeline(tiny_model, config)
    places = [textured(s) for s in range(4)]
    frames = [Frame(float(t), places[p], "cam", depth=DEPTH, camera=CAMERA)
              for t, p in enumerate(ROUTE)]  # fmt: skip
    run = ReplayRun(ReplaySummary("bag", "/cam", None, None))
    run.pending.extend(BagFrame(i, f.stamp, 0, "cam", f.rgb, None) for i, f in enumerate(frames))
    with tqdm(disable=True) as bar:
        drive(run, pipe, iter(frames), 8, None, bar)
    assert run.represented == [(4.0, 4), (5.0, 4)]  # 4 keyframes stored before each
    assert run.summary.keyframes == 4 and run.summary.loops == 2
    accepted = [r for r in run.records if r.accepted]
    assert [(r.query_id, r.query_stamp, r.match_id) for r in accepted] == [
        (-1, 4.0, 0),
        (-1, 5.0, 1),
    ]
    assert [r.query_stamp for r in run.global_top1][-2:] == [4.0, 5.0]  # queries of the map
    truth = PoseTrack()
    for t, p in enumerate(ROUTE):
        truth.add(float(t), (30.0 * p, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    keyframes = _keyframes(pipe, run, truth, 0.1)
    assert [(k.id, k.stamp, k.stored) for k in keyframes][4:] == [(4, 4.0, False), (4, 5.0, False)]
    ev = evaluate_loops(run.records, keyframes, gt_radius=10.0, exclusion_s=2.5)
    assert (ev.positives, ev.true_accepted, ev.false_accepted) == (2, 2, 0)
    assert ev.recall == 1.0 and ev.labels[-2:] == [True, True]
    pipe.close()
