"""The pipeline's relative poses: features stored in the map, poses for accepted loops only,
counted input problems, maps saved with and without features (tiny random network, exact
repeats as loops, see exact_match.py)."""

from __future__ import annotations

import sqlite3
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import textured
from exact_match import EXACT_MATCH

from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.geometry.relpose import PoseConfig
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import Candidate

H, W = 120, 160
CAMERA = CameraModel(W, H, 100.0, 100.0, 79.5, 59.5)
DEPTH = np.full((H, W), 4.0, np.float32)  # a wall 4 m in front of the camera


@pytest.fixture
def model(tiny_model):
    return tiny_model


PLACES = [textured(s) for s in range(4)]


def frames(order, **extra) -> list[Frame]:
    return [Frame(float(t), PLACES[p], "cam", **extra) for t, p in enumerate(order)]


def accepted(outcomes):
    return [o.loop for o in outcomes if o.loop is not None and o.loop.accepted]


def pipeline(model, **geometry) -> LoopClosurePipeline:
    return LoopClosurePipeline(
        model, DetectorConfig(**EXACT_MATCH), geometry=GeometryConfig(**geometry)
    )


def test_a_revisit_with_depth_gets_a_metric_identity_pose(model):
    pipe = pipeline(model)
    out = list(pipe.process_many(frames([0, 1, 2, 3, 0], depth=DEPTH, camera=CAMERA)))
    (loop,) = accepted(out)
    assert (loop.query_id, loop.match_id, loop.pose_status, loop.pose_reason) == (
        4,
        0,
        "metric",
        "",
    )
    assert abs(loop.tx) + abs(loop.ty) + abs(loop.tz) < 1e-3 and loop.qw == pytest.approx(1.0)
    assert loop.pose_inliers >= 30 and len(loop.covariance) == 36
    assert np.all(np.isfinite(loop.covariance))
    assert "pose" in out[4].timings_ms and "pose" not in out[3].timings_ms  # accepted loops only
    assert "features" in out[0].timings_ms
    assert pipe.counts.pose_metric == 1
    assert pipe.place_map.feature_stats()[0] == 5  # every keyframe's features are kept


@pytest.mark.parametrize(
    ("extra", "count", "reason"),
    [
        (dict(depth=DEPTH), None, "no intrinsics for the query keyframe (no camera_info"),
        (dict(depth=DEPTH, camera=replace(CAMERA, width=320)), "intrinsics_wrong_size",
         "no intrinsics for the query keyframe"),
        (dict(depth=DEPTH[:60], camera=CAMERA), "depth_wrong_size", "degenerate motion: "),
    ],
)  # fmt: skip
def test_bad_inputs_give_reasons_and_counts_not_poses(model, extra, count, reason):
    pipe = pipeline(model)
    (loop,) = accepted(pipe.process_many(frames([0, 1, 2, 0], **extra)))
    assert loop.pose_status == "" and loop.pose_reason.startswith(reason), loop.pose_reason
    assert loop.covariance == () and np.isnan(loop.tx)
    if count:
        assert getattr(pipe.counts, count) == 4
    assert pipe.counts.pose_none == 1


def test_without_depth_a_revisit_from_the_same_spot_is_degenerate(model):
    # The same image twice: no parallax, so no translation direction (and no made-up one).
    (loop,) = accepted(pipeline(model).process_many(frames([0, 1, 2, 0], camera=CAMERA)))
    assert loop.pose_status == "" and loop.pose_reason.startswith("degenerate motion")


def test_relative_pose_off_extracts_nothing(model):
    pipe = pipeline(model, relative_pose=False)
    out = list(pipe.process_many(frames([0, 1, 2, 0], depth=DEPTH, camera=CAMERA)))
    (loop,) = accepted(out)
    assert loop.pose_status == "" and loop.pose_reason == "" and loop.pose_inliers == -1
    assert all("features" not in o.timings_ms for o in out)
    assert pipe.place_map.feature_stats() == (0, 0)


def test_geometric_verification_uses_the_stored_features(model):
    config = DetectorConfig(**EXACT_MATCH, geometric_verification=True, min_inliers=20)
    pipe = LoopClosurePipeline(model, config, geometry=GeometryConfig(relative_pose=False))
    (loop,) = accepted(pipe.process_many(frames([0, 1, 2, 0])))
    assert loop.inliers >= 20 and loop.inlier_ratio > 0.9


def test_poses_after_save_and_load_come_from_the_features_on_disk(model, tmp_path: Path):
    first = pipeline(model)
    list(first.process_many(frames([0, 1, 2], depth=DEPTH, camera=CAMERA)))
    first.save_map(tmp_path / "map")
    first.close()
    second = pipeline(model)
    second.load_map(tmp_path / "map")
    later = frames([3, 0], depth=DEPTH, camera=CAMERA)
    for i, f in enumerate(later):
        f.stamp = 10.0 + i
    (loop,) = accepted(second.process_many(later))
    assert (loop.match_id, loop.pose_status) == (0, "metric")
    second.close()


def strip_features(map_dir: Path) -> None:
    """Make a saved map's keyframes look like ones saved before features were kept (what a
    format-2 map without a features table converts to)."""
    with sqlite3.connect(map_dir / "map-1.sqlite") as conn:
        conn.execute("DELETE FROM features")
    conn.close()


def test_an_old_map_without_features_loads_and_poses_come_for_new_keyframes(model, tmp_path):
    first = pipeline(model)
    list(first.process_many(frames([0, 1], depth=DEPTH, camera=CAMERA)))
    first.save_map(tmp_path / "map")
    first.close()
    strip_features(tmp_path / "map")
    pipe = pipeline(model)
    assert pipe.load_map(tmp_path / "map") == 2
    assert pipe.place_map.feature_stats() == (0, 0)
    later = [replace(f, stamp=10.0 + i) for i, f in
             enumerate(frames([2, 3, 0, 2], depth=DEPTH, camera=CAMERA))]  # fmt: skip
    old, new = accepted(pipe.process_many(later))
    assert (old.match_id, old.pose_status) == (0, "")
    assert old.pose_reason.startswith("match keyframe has no features (kept only for keyframes")
    assert (new.match_id, new.pose_status) == (2, "metric")  # added after the load
    pipe.save_map(tmp_path / "map")  # and it saves in the current format
    pipe.close()


def _match(kf_id: int) -> Candidate:
    """A live-map candidate of the pipeline's default identity."""
    return Candidate(kf_id, 0.0, "cam", 1.0, 1, robot="robot", session="default")


def test_monocular_scale_baselines_come_from_the_map_keyframes_next_to_the_match(model):
    # Keyframes 0..4 every 1 m along x; keyframe 3 has no odometry pose (it is not used).
    pipe = pipeline(model)
    poses = [(float(i), 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) for i in range(5)]
    poses[3] = None
    order = frames([0, 1, 2, 3, 1], camera=CAMERA)
    batch = [replace(f, pose=p) for f, p in zip(order, poses, strict=True)]
    list(pipe.process_many(batch))
    near = pipe.scale_neighbours(_match(2))
    # least turn, then the longest baseline first
    assert [(n.id, n.baseline_m, n.turn_deg) for n in near] == [(0, 2.0, 0.0), (4, 2.0, 0.0),
                                                                (1, 1.0, 0.0)]  # fmt: skip
    assert near[0].load().kind == "sift" and len(near[0].load()) > 0
    no_scale = pipeline(model, pose=PoseConfig(odometry_scale=False))
    list(no_scale.process_many(batch))
    assert no_scale.scale_neighbours(_match(2)) == []
