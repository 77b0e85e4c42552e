"""A rig of several cameras (issue 49): loops posed between the two keyframes' bases with the
covariance carried through (checked against finite differences and the pose graph's own
camera_to_base path), rig keyframes assembled from several cameras and run through the one
pipeline: batched encoding, every camera's keyframes in one map, loops across cameras."""

from __future__ import annotations

import numpy as np
import pytest
from bag_fixtures import textured
from exact_match import EXACT_MATCH

from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.rotations import exp_so3, matrix_quaternion, quaternion_matrix
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.loops.rig import Rig, RigCamera, compose_base, to_base
from pair_vpr_ros.loops.rig_frames import RigAssembler, assemble
from pair_vpr_ros.messages.factor import factor_from_record

FRONT = (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)  # optical frame looking along base x
REAR = (-1.0, 0.0, 1.6, 0.5, 0.5, -0.5, -0.5)  # 1 m behind, looking along -x
RIG = Rig((RigCamera("front", FRONT), RigCamera("rear", REAR)))


def _pose(rng) -> tuple[float, ...]:
    q = rng.normal(size=4)
    return (*rng.normal(size=3), *(q / np.linalg.norm(q)))


def _record(t: np.ndarray, cov: np.ndarray, query: int, match: int) -> LoopRecord:
    q = matrix_quaternion(t[:3, :3])
    return LoopRecord(
        5, 10.0, "rear", 1, 2.0, "front", pair_score=1.0, global_similarity=0.9, rank_before=1,
        rank_after=1, accepted=True, pose_status="metric", tx=t[0, 3], ty=t[1, 3], tz=t[2, 3],
        qx=q[0], qy=q[1], qz=q[2], qw=q[3], covariance=tuple(cov.ravel()), query_camera=query,
        match_camera=match,
    )  # fmt: skip


def _matrix(pose) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = quaternion_matrix(pose[3:]), pose[:3]
    return out


def test_a_loop_between_cameras_is_given_between_the_bases() -> None:
    rng = np.random.default_rng(3)
    t = _matrix(_pose(rng))
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + np.eye(6)
    record = _record(t, cov, query=1, match=0)
    to_base(record, RIG)
    want = _matrix(FRONT) @ t @ np.linalg.inv(_matrix(REAR))
    got = factor_from_record(record)
    np.testing.assert_allclose(got.matrix(), want, atol=1e-9)
    assert (got.query_frame_id, got.match_frame_id) == ("base_link", "base_link")
    assert (got.query_camera, got.match_camera, record.pose_frame) == (1, 0, "base_link")
    # the covariance: first-order propagation, checked against finite differences of the
    # composition under the record's perturbation (R' = Exp(d_r) R, t' = t + d_t)
    _, base_cov = compose_base(t, cov, FRONT, REAR)
    jac = np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        moved = t.copy()
        moved[:3, :3] = exp_so3(d[3:]) @ t[:3, :3]
        moved[:3, 3] += d[:3]
        out = _matrix(FRONT) @ moved @ np.linalg.inv(_matrix(REAR))
        rot = out[:3, :3] @ want[:3, :3].T
        jac[:3, k] = (out[:3, 3] - want[:3, 3]) / 1e-6
        jac[3:, k] = np.array([rot[2, 1], rot[0, 2], rot[1, 0]]) / 1e-6
    np.testing.assert_allclose(base_cov, jac @ cov @ jac.T, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(got.covariance_matrix(), base_cov, atol=1e-9)


def test_one_camera_gives_what_the_pose_graph_makes_of_camera_to_base() -> None:
    gtsam = pytest.importorskip("gtsam")
    from pair_vpr_ros.posegraph.transforms import pose3, transform_covariance

    rng = np.random.default_rng(5)
    t = _matrix(_pose(rng))
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + np.eye(6)
    camera = factor_from_record(_record(t, cov, 0, 0))
    record = _record(t, cov, 0, 0)
    to_base(record, RIG)
    base = factor_from_record(record)
    c = pose3(FRONT)
    graph = c.compose(gtsam.Pose3(camera.matrix())).compose(c.inverse())
    np.testing.assert_allclose(base.matrix(), graph.matrix(), atol=1e-9)
    expect = transform_covariance(camera.gtsam_covariance(), c)
    np.testing.assert_allclose(base.gtsam_covariance(), expect, rtol=1e-9, atol=1e-9)


def test_records_without_a_pose_or_an_extrinsic_stay_as_they_are() -> None:
    record = _record(np.eye(4), np.eye(6), 1, 0)
    record.pose_status = ""
    to_base(record, RIG)
    assert record.pose_frame == "" and record.tx == 0.0
    record = _record(np.eye(4), np.eye(6), 2, 0)  # a camera this rig does not have
    to_base(record, RIG)
    assert record.pose_frame == ""


H, W = 120, 160
CAMERA = CameraModel(W, H, 100.0, 100.0, 79.5, 59.5)
DEPTH = np.full((H, W), 4.0, np.float32)
PLACES = [textured(s) for s in range(8)]


def _rig_frames(front: list[int], rear: list[int]) -> list[Frame]:
    """Frames of both cameras, one instant a second, each with depth and intrinsics."""
    out = []
    for t, (f, r) in enumerate(zip(front, rear, strict=True)):
        for cam, place in ((0, f), (1, r)):
            out.append(Frame(float(t), PLACES[place], RIG.cameras[cam].name, depth=DEPTH,
                             camera=CAMERA, camera_id=cam))  # fmt: skip
    return out


def test_the_rig_pipeline_finds_a_revisit_driven_the_other_way(tiny_model) -> None:
    encoded = []
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT_MATCH), rig=RIG)
    encode = pipe.encode
    pipe.encode = lambda images: encoded.append(len(images)) or encode(images)
    # the rear camera sees place 5 at t=1; driven back, the front camera sees it at t=4
    frames = _rig_frames([0, 1, 2, 3, 5], [4, 5, 6, 7, 1])
    out = list(pipe.process_groups(assemble(frames, RIG), batch_size=1))
    assert encoded == [2] * 5  # each rig keyframe one batch, even at batch size 1
    assert [o.keyframe_id for o in out] == list(range(10))
    assert [m.camera for m in pipe.place_map.all_meta()] == [0, 1] * 5
    loops = [o.loop for o in out if o.loop is not None and o.loop.accepted]
    assert [(r.query_id, r.query_camera, r.match_id, r.match_camera) for r in loops] == [
        (8, 0, 3, 1), (9, 1, 2, 0)]  # fmt: skip
    front_rear = loops[0]  # posed between the cameras (identity: the same view), then bases
    assert front_rear.pose_status == "metric" and front_rear.pose_frame == "base_link"
    want = _matrix(REAR) @ np.linalg.inv(_matrix(FRONT))
    np.testing.assert_allclose(factor_from_record(front_rear).matrix(), want, atol=2e-3)
    assert pipe.counts.keyframes == 10 and pipe.counts.encoded == 10


def test_a_rig_keyframe_is_skipped_only_when_every_camera_repeats(tiny_model) -> None:
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT_MATCH), rig=RIG)
    frames = _rig_frames([0, 0, 0], [1, 1, 2])  # t=1: both repeat; t=2: the rear moved on
    out = list(pipe.process_groups(assemble(frames, RIG)))
    assert [o.skipped for o in out] == ["", "", "similar to previous keyframe"] * 1 + [
        "similar to previous keyframe", "", ""]  # fmt: skip
    assert [o.keyframe_id for o in out] == [0, 1, None, None, 2, 3]


def test_the_rerank_budget_is_shared_by_the_cameras_of_a_rig_keyframe(tiny_model) -> None:
    config = DetectorConfig(**{**EXACT_MATCH, "rerank_budget_ms": 50.0})
    pipe = LoopClosurePipeline(tiny_model, config, rig=RIG)
    shares = []
    score = pipe.detector.score
    pipe.detector.score = lambda *a, **k: shares.append(pipe.detector.budget_ms) or score(*a, **k)
    out = list(pipe.process_groups(assemble(_rig_frames([0, 1, 2, 3, 0], [4, 5, 6, 7, 4]), RIG)))
    spent = out[8].timings_ms["rerank"]  # the front camera's query at t=4, the first to score
    assert shares == [25.0, pytest.approx(max(50.0 - spent, 1e-6))]  # half, then what is left
    assert pipe.detector.budget_ms is None  # outside a rig keyframe: the config's budget


def test_the_assembler_groups_by_stamp_and_never_waits_for_a_silent_camera() -> None:
    clock = [0.0]
    asm = RigAssembler(RIG, clock=lambda: clock[0])
    frame = lambda t, cam: Frame(t, PLACES[0], RIG.names[cam], camera_id=cam)  # noqa: E731
    assert asm.add(frame(1.0, 0)) == []
    (group,) = asm.add(frame(1.01, 1))  # within the tolerance: complete, out at once
    assert [(f.stamp, f.camera_id) for f in group] == [(1.0, 0), (1.01, 1)]
    assert asm.add(frame(1.1, 0)) == []  # the rear camera stops publishing
    clock[0] = 0.1
    assert asm.poll() == []  # waits up to max_delay (0.2 s of wall clock)
    clock[0] = 0.25
    (alone,) = asm.poll()
    assert [f.camera_id for f in alone] == [0]
    assert asm.add(frame(1.1, 1)) == []  # came after its rig keyframe went: dropped
    assert asm.counts.to_dict() == {
        "keyframes": 2, "incomplete": 1, "missing": {"rear": 1}, "late": {"rear": 1},
        "apart": {}, "max_apart_ms": 0.0, "frame_id_clash": 0,
    }  # fmt: skip
