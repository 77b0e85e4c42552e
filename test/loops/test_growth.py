"""The map's growth policy (issue 34 part 3, loops/growth.py, place_map/growth/): a revisit of a
stored place in its appearance is represented, not stored; a new appearance is stored; links
and signatures are saved with the map; `info` counts them; `compact` applies the policy to a
saved map (tiny random network, exact repeats as loops, depth for metric poses)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from bag_fixtures import textured
from exact_match import EXACT_MATCH

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.fleet.messages import ScoreRequest
from pair_vpr_ros.fleet.owner import score_request
from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.rotations import exp_so3, log_so3
from pair_vpr_ros.loops import pipeline as pipeline_module
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.growth import appearance_signature, lent_covariance, shift_pose
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import IndexConfig, PlaceMap
from pair_vpr_ros.place_map.growth.compact import compact_map
from pair_vpr_ros.place_map.growth.policy import GrowthConfig, find_representative
from pair_vpr_ros.place_map.growth.tables import compose, invert
from pair_vpr_ros.place_map.info import map_info
from pair_vpr_ros.place_map.merge import merge_maps

H, W = 120, 160
CAMERA = CameraModel(W, H, 100.0, 100.0, 79.5, 59.5)
DEPTH = np.full((H, W), 4.0, np.float32)  # a wall 4 m in front of the camera
PLACES = [textured(s) for s in range(4)]
ROUTE = [0, 1, 2, 3, 0]  # frame 4 revisits place 0


def drive(model, growth: str, order=ROUTE, codec: str = "q4", place_map=None):
    config = DetectorConfig(**{**EXACT_MATCH, "map_growth": growth})
    pipe = LoopClosurePipeline(model, config, place_map=place_map,
                               index=IndexConfig(dense_codec=codec))  # fmt: skip
    frames = [Frame(float(t), PLACES[p], "cam", depth=DEPTH, camera=CAMERA)
              for t, p in enumerate(order)]  # fmt: skip
    return pipe, list(pipe.process_many(frames))


def test_a_revisit_in_the_same_light_is_represented_not_stored(tiny_model):
    pipe, out = drive(tiny_model, "places")
    revisit = out[4]
    assert revisit.keyframe_id is None and revisit.represented_by == 0
    assert revisit.loop.accepted and revisit.loop.query_id == -1  # published, as found
    assert revisit.loop.match_id == 0 and revisit.loop.pose_status == "metric"
    m = pipe.place_map
    assert len(m) == 4 and pipe.counts.represented == 1 and pipe.counts.keyframes == 5
    (row,) = m.growth.represented()
    assert (row.stamp, row.representative) == (4.0, 0) and row.distance < 1e-3  # float16
    # a later query of the place finds the representative
    assert m.search(pipe.encode([PLACES[0]])[1][0], 1)[0][0] == 0
    pipe.close()


@pytest.mark.parametrize("threshold, stored", [(10.0, True), (4.0, False)])
def test_a_revisit_found_only_through_the_sequence_margin_is_stored(
    tiny_model, monkeypatch, threshold, stored
):
    """Place 0's revisit scores 12, place 1's 5: at threshold 10 the second loop is accepted
    only through sequence_margin (it continues the first), a view the model barely knows, so
    keyframe 1 does not represent it and it is stored; at threshold 4 it is represented."""
    scores = iter([12.0, 5.0])
    fake = lambda self, dense, ids: np.array([next(scores) for _ in ids])  # noqa: E731
    monkeypatch.setattr(LoopClosurePipeline, "pair_scores", fake)
    config = DetectorConfig(**{**EXACT_MATCH, "map_growth": "places", "score_threshold": threshold,
                               "sequence_margin": 10.0})  # fmt: skip
    pipe = LoopClosurePipeline(tiny_model, config)
    frames = [Frame(float(t), PLACES[p], "cam", depth=DEPTH, camera=CAMERA)
              for t, p in enumerate([0, 1, 2, 3, 0, 1])]  # fmt: skip
    out = list(pipe.process_many(frames))
    assert out[4].represented_by == 0 and out[4].loop.pair_score == 12.0
    loop = out[5].loop
    assert loop.accepted and loop.match_id == 1 and loop.pair_score == 5.0
    assert loop.pose_status == "metric"
    if stored:
        assert out[5].represented_by is None and out[5].keyframe_id == 4
    else:
        assert out[5].represented_by == 1 and out[5].keyframe_id is None
    pipe.close()


def test_a_new_appearance_of_a_known_place_is_stored(tiny_model, monkeypatch):
    dusk = (PLACES[0] * 0.55).astype(np.uint8)  # the revisit's light, for its signature only
    real = appearance_signature

    def signature(rgb):
        return real(dusk) if rgb is PLACES[0] and signature.calls == 4 else real(rgb)

    def counted(rgb):
        out = signature(rgb)
        signature.calls += 1
        return out

    signature.calls = 0
    monkeypatch.setattr(pipeline_module, "appearance_signature", counted)
    pipe, out = drive(tiny_model, "places")
    assert out[4].keyframe_id == 4 and out[4].represented_by is None and out[4].loop.accepted
    m = pipe.place_map
    assert m.growth.counts().represented == 0
    assert [k for k, _ in m.growth.links(4)] == [0]  # the two appearances linked
    # stored with its descriptor and dense tokens, but keyframe 0 lends it its features
    assert m.features(4) == b"" and m.features(0) != b""
    source, t_4_0 = pipe.growth.feature_source(m, 4)
    assert source == 0 and t_4_0 == pytest.approx((0, 0, 0, 0, 0, 0, 1), abs=1e-2)
    lent, shift = pipe.match_features(Candidate(4, 4.0, "cam", 1.0, 1))
    assert shift == (0, t_4_0) and lent is not None  # (source id, T_match_source)
    assert lent.keypoints.shape == pipe.match_features(Candidate(0, 0.0, "cam", 1.0, 1))[
        0].keypoints.shape  # fmt: skip
    assert pipe.match_features(Candidate(1, 1.0, "cam", 1.0, 1))[1] is None  # its own
    # issue 48, loose end 3: another robot's request for keyframe 4 is answered as the local
    # path answers: posed with its lender's features, composed into its own frame
    req = ScoreRequest("b", "s1", b"", 0, "robot", "default", 7, 50.0, [4], [1.0],
                       m.get_dense([0])[0], m.features(0))  # fmt: skip
    loop, response = score_request(pipe, req, "robot", "default")
    rec = loop.record
    assert (rec.match_id, rec.accepted, rec.pose_status, response.pose_status) == (
        4, True, "metric", "metric",
    )  # fmt: skip
    pose = (rec.tx, rec.ty, rec.tz, rec.qx, rec.qy, rec.qz, rec.qw)
    assert pose == pytest.approx(compose(t_4_0, (0, 0, 0, 0, 0, 0, 1)), abs=2e-2)
    pipe.close()
    # with the policy off every keyframe keeps its own features
    pipe, out = drive(tiny_model, "all")
    assert pipe.place_map.features(4) != b""
    pipe.close()


def test_a_loop_posed_with_lent_features_is_composed_into_the_match_s_frame():
    quarter = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))  # 90 deg about z
    record = LoopRecord(-1, 9.0, "cam", 4, 4.0, "cam", pair_score=1.0, global_similarity=1.0,
                        rank_before=1, rank_after=1, accepted=True, pose_status="metric",
                        tx=1.0, ty=0.0, tz=0.0, qx=0.0, qy=0.0, qz=0.0, qw=1.0)  # fmt: skip
    shift_pose(record, (0.0, 0.0, 2.0, *quarter))  # T_match_source
    assert (record.tx, record.ty, record.tz) == pytest.approx((0.0, 1.0, 2.0))
    assert (record.qx, record.qy, record.qz, record.qw) == pytest.approx((0, 0, *quarter[2:]))
    assert record.covariance == ()  # none given, none made up
    record.covariance = tuple(np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5]).ravel())
    shift_pose(record, (0.0, 0.0, 0.0, *quarter))  # from (0, 1, 2): T_source_query's t
    cov = np.asarray(record.covariance).reshape(6, 6)
    # turned by 90 deg about z (x <-> y), the link's error added: [v]x e_rot with v = (-1, 0, 2)
    assert np.diag(cov)[3:] == pytest.approx([4e-5, 2e-5, 6e-5])
    assert cov[2, 2] == pytest.approx(
        2 * 3e-4 + 1e-5
    )  # z: its own twice, and the lever v x e_rot: e_ry
    record.pose_status = "scale-free"  # a direction cannot be composed: no pose then
    shift_pose(record, (0.0, 0.0, 2.0, *quarter))
    assert record.pose_status == "" and math.isnan(record.tx) and record.covariance == ()
    assert record.pose_reason == "scale-free pose to the features of a linked keyframe"


def test_lent_covariance_matches_sampled_link_and_loop_errors():
    """Loop errors drawn from the loop's covariance (along the source camera's axes), link
    errors from the same turned into the match's frame (the link's is taken as the loop's),
    composed exactly: their spread is what lent_covariance says."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6)) * np.r_[0.02, 0.02, 0.02, 0.01, 0.01, 0.01][:, None]
    cov = a @ a.T
    r_link, t_link = exp_so3(np.array([0.3, -0.2, 1.1])), np.array([0.5, -1.0, 2.0])
    r, t = exp_so3(np.array([0.1, 0.4, -0.2])), np.array([1.5, 0.3, -0.7])
    b = np.kron(np.eye(2), r_link)
    loops = rng.multivariate_normal(np.zeros(6), cov, 20000)
    links = rng.multivariate_normal(np.zeros(6), b @ cov @ b.T, 20000)
    true_r, true_t = r_link @ r, t_link + r_link @ t
    errors = []
    for loop, link in zip(loops, links, strict=True):
        r_l, t_l = exp_so3(link[3:]) @ r_link, t_link + link[:3]
        r_q, t_q = exp_so3(loop[3:]) @ r, t + loop[:3]
        errors.append(np.r_[t_l + r_l @ t_q - true_t, log_so3(r_l @ r_q @ true_r.T)])
    got = np.cov(np.array(errors).T)
    assert np.allclose(got, lent_covariance(cov, r_link, t), atol=0.03 * np.abs(got).max())


def test_policy_all_stores_every_keyframe_with_signatures_and_links(tiny_model):
    pipe, out = drive(tiny_model, "all")
    m = pipe.place_map
    assert [o.keyframe_id for o in out] == [0, 1, 2, 3, 4] and out[4].loop.query_id == 4
    counts = m.growth.counts()
    assert (counts.signatures, counts.links, counts.represented) == (5, 1, 0)
    ((other, pose),) = m.growth.links(0)  # read from the older end: T_4_0
    assert other == 4 and np.allclose(pose[:3], 0, atol=1e-3)
    pipe.close()


def test_links_signatures_and_represented_rows_survive_save_and_load(tiny_model, tmp_path):
    pipe, _ = drive(tiny_model, "places", order=[0, 1, 2, 3, 0, 1])
    pipe.save_map(tmp_path / "m")
    before = [(k, pipe.place_map.growth.links(k)) for k in range(4)]
    pipe.close()
    with PlaceMap.load(tmp_path / "m", read_only=True) as m:
        assert m.growth.counts().represented == 2 and len(m) == 4
        assert [(k, m.growth.links(k)) for k in range(4)] == before
        np.testing.assert_allclose(m.growth.signature(1), appearance_signature(PLACES[1]),
                                   atol=1e-3)  # fmt: skip
    # continued after a load: the loaded map's signatures represent the next revisit
    loaded = PlaceMap.load(tmp_path / "m")
    pipe, out = drive(tiny_model, "places", order=[2], place_map=loaded)
    assert out[0].represented_by is None  # one frame: no loop, so stored
    pipe.close()


def test_info_counts_stored_represented_and_bytes(tiny_model, tmp_path, capsys):
    pipe, _ = drive(tiny_model, "places")
    pipe.save_map(tmp_path / "m")
    pipe.close()
    info = map_info(tmp_path / "m")
    assert (info.keyframes, info.represented, info.links, info.with_signatures) == (4, 1, 0, 4)
    assert info.bytes_per_keyframe == info.total_bytes / 4
    assert main(["info", str(tmp_path / "m"), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert (data["represented"], data["bytes_per_keyframe"]) == (1, info.bytes_per_keyframe)
    assert main(["info", str(tmp_path / "m")]) == 0
    assert "keyframes: 4 stored (4 with features, 4 with an appearance signature), 1 " \
        "represented (not stored), 0 links" in capsys.readouterr().out  # fmt: skip


def test_compact_applies_the_policy_and_the_codec_and_round_trips(tiny_model, tmp_path, capsys):
    pipe, _ = drive(tiny_model, "all", order=[0, 1, 2, 3, 0, 1], codec="f16")
    pipe.save_map(tmp_path / "in")
    src = pipe.place_map
    args = ["compact", str(tmp_path / "in"), "--out", str(tmp_path / "out")]
    assert main([*args, "--exclude-recent-s", "2.5"]) == 0  # EXACT_MATCH's window
    assert capsys.readouterr().out.startswith(
        f"compacted 6 keyframes into {tmp_path / 'out'}: 4 stored, 2 represented (2 new), "
        "dense tokens p4; "  # the default codec
    )
    with PlaceMap.load(tmp_path / "out", read_only=True) as m:
        assert len(m) == 4 and m.index_config.dense_codec == "p4"
        assert [r.representative for r in m.growth.represented()] == [0, 1]
        for i in range(4):
            assert m.meta(i) == src.meta(i) and m.features(i) == src.features(i)
            np.testing.assert_allclose(m.get_desc([i]), src.get_desc([i]), atol=1e-6)
            ref = src.get_dense([i]).astype(np.float32)
            assert (
                np.abs(m.get_dense([i]).astype(np.float32) - ref).max() < 0.2 * np.abs(ref).max()
            )
    pipe.close()
    # again with the policy off: only re-encoded, every keyframe kept
    result = compact_map(tmp_path / "in", tmp_path / "all", codec="q4", policy=False)
    assert (result.stored, result.represented) == (6, 0)
    # the default window (30 s): keyframes 0-5 s apart of one session never represent each other
    result = compact_map(tmp_path / "in", tmp_path / "recent")
    assert (result.stored, result.represented) == (6, 0)


def test_a_link_keeps_its_re_rank_score_and_compact_applies_the_threshold(tiny_model, tmp_path):
    """Issue 48, loose end 2: each link keeps the re-rank score with which its keyframe's query
    recognised the match (the live rule's third condition); compact represents a keyframe only
    by one it recognised at or above --score-threshold, as the live map_growth would have."""
    pipe, out = drive(tiny_model, "all", order=[0, 1, 2, 3, 0, 1], codec="f16")
    pipe.save_map(tmp_path / "in")
    scores = []
    for q in (4, 5):
        ((match, _, score),) = pipe.place_map.growth.scored_links(q)
        assert (match, score) == (q - 4, out[q].loop.pair_score)  # global_weight 0
        scores.append(score)
    pipe.close()
    args = ["compact", str(tmp_path / "in"), "--exclude-recent-s", "2.5", "--score-threshold"]
    assert main([*args, str(min(scores)), "--out", str(tmp_path / "at")]) == 0
    assert main([*args, str(max(scores) + 1.0), "--out", str(tmp_path / "above")]) == 0
    with PlaceMap.load(tmp_path / "at", read_only=True) as at:
        assert (len(at), at.growth.counts().represented) == (4, 2)
    with PlaceMap.load(tmp_path / "above", read_only=True) as above:
        assert (len(above), above.growth.counts().represented) == (6, 0)
        assert [s for _, _, s in above.growth.scored_links(4)] == [scores[0]]  # carried


def test_compact_of_a_map_without_signatures_only_re_encodes(tmp_path, capsys):
    m = PlaceMap(desc_dim=8, dense_shape=(2, 3), fingerprint="fp", index=IndexConfig(
        dense_codec="f16"))  # fmt: skip
    from pair_vpr_ros.place_map import KeyframeMeta

    for i in range(3):
        m.add(np.eye(8)[i], np.ones((2, 3)), KeyframeMeta(stamp=float(i), frame_id="cam"))
    m.save(tmp_path / "in")
    m.close()
    assert main(["compact", str(tmp_path / "in"), "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert captured.err == (
        f"note: {tmp_path / 'in'} has no appearance signatures (saved before map_growth): its "
        "keyframes are only re-encoded\n"
    )
    assert "3 stored, 0 represented (0 new), dense tokens p4" in captured.out


def test_the_rule_follows_one_link_and_checks_pose_and_appearance():
    sig = np.zeros(96, np.float32)
    turn = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # 1 m to the side
    links = {7: [(3, invert(turn))]}.get  # keyframe 3 is linked to 7 (T_3_7)
    signatures = {3: sig, 7: sig + 0.5}.get  # 7: other light; 3: Q's light
    config = GrowthConfig()
    found = find_representative(sig, [(7, turn)], lambda k: links(k, []), signatures, config)
    assert found == (3, 0.0)  # via the link; T_3_Q = T_3_7 T_7_Q = identity
    assert compose(invert(turn), turn) == pytest.approx((0, 0, 0, 0, 0, 0, 1))
    far = (9.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert find_representative(sig, [(3, far)], lambda k: [], signatures, config) is None
    assert find_representative(sig + 0.5, [(3, turn)], lambda k: [], signatures, config) is None
    yaw = math.radians(20.0) / 2  # 20 deg: beyond a representative, within a lender
    view = (1.0, 0.0, 0.0, 0.0, math.sin(yaw), 0.0, math.cos(yaw))
    assert find_representative(sig, [(3, view)], lambda k: [], signatures, config) is None
    assert config.shares(view) and not config.near(view) and not config.shares(far)


def test_compact_keeps_a_keyframe_that_lends_its_features(tmp_path):
    """Keyframe 1 is represented by 0 (same place, light and view), but 2, stored without
    features, takes its geometry from 1: compact keeps 1; with 2 gone it would drop it."""
    from pair_vpr_ros.place_map import KeyframeMeta

    def saved(lending: bool, name: str):
        m = PlaceMap(desc_dim=8, dense_shape=(2, 3), fingerprint="fp")
        sig, same = np.zeros(96, np.float32), (0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        for i, session in enumerate(("a", "b", "c")):
            meta = KeyframeMeta(stamp=100.0 * i, frame_id="cam", session=session)
            m.add(np.eye(8)[i], np.ones((2, 3)), meta, b"" if i == 2 and lending else b"FEAT")
            m.growth.add_signature(i, sig + (0.5 if i == 2 else 0.0))  # 2: another light
        m.growth.add_link(1, 0, same)
        m.growth.add_link(2, 1, same)
        m.save(tmp_path / name)
        m.close()
        return compact_map(tmp_path / name, tmp_path / f"{name}-out")

    assert (saved(True, "lent").stored, saved(False, "own").stored) == (3, 2)
    # merge carries the links, ids shifted: keyframe 2 of the second input keeps its lender
    merge_maps([tmp_path / "own", tmp_path / "lent"], tmp_path / "merged")
    with PlaceMap.load(tmp_path / "merged", read_only=True) as m:
        assert len(m) == 6 and m.features(5) == b""
        assert [k for k, _ in m.growth.links(5)] == [4] and m.growth.links(1)[0][0] == 0
        assert m.growth.counts().signatures == 6


@pytest.mark.parametrize(
    ("field", "value"),
    [("max_rotation_deg", -1.0), ("share_rotation_deg", math.nan),
     ("share_translation_m", math.inf), ("max_appearance", -0.1)],
)  # fmt: skip
def test_growth_config_refuses_negative_or_non_finite_limits(field, value):
    with pytest.raises(ConfigError) as err:
        GrowthConfig(**{field: value})
    assert str(err.value) == f"growth {field}={value!r} must be a finite number >= 0"
