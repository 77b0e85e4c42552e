"""Start-up notes about camera inputs (fallback intrinsics without distortion, a silent
camera_info topic, the demo model on other images) and the replay's exclusion-window note."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pair_vpr_ros.geometry.camera_notes import (
    camera_info_silence_note,
    demo_model_note,
    demo_weights_id,
    fallback_intrinsics_note,
)
from pair_vpr_ros.offline.replay.notes import exclusion_notes
from pair_vpr_ros.params.configs import defaults


def test_fallback_intrinsics_without_distortion_are_named():
    v = defaults()
    assert fallback_intrinsics_note(v).startswith("relative poses are off: neither")
    v["camera_fx"] = 500.0
    assert fallback_intrinsics_note(v).startswith(
        "relative poses use the fallback camera_* intrinsics with no distortion"
    )
    assert fallback_intrinsics_note({**v, "camera_distortion": "0.1, -0.2, 0, 0"}) == ""
    assert fallback_intrinsics_note({**v, "camera_info_topic": "/cam/info"}) == ""
    assert fallback_intrinsics_note({**v, "relative_pose": False}) == ""


def test_silent_camera_info_note():
    assert camera_info_silence_note("/cam/info", 5.2, False) == (
        "camera_info_topic /cam/info: no valid CameraInfo within 5 s of the first frame: is the "
        "topic name right and the driver publishing? no relative poses until it does (or set "
        "the camera_* intrinsics)"
    )
    assert camera_info_silence_note("/c", 6, True).endswith("intrinsics are used meanwhile")


def test_demo_model_note_only_for_the_demo_model_on_other_images():
    demo = demo_weights_id()
    assert demo.startswith("sha256:") and len(demo) == 23
    real = np.zeros((480, 640, 3), np.uint8)
    note = demo_model_note(f"{demo}|small|112px", real)
    assert note.startswith("the weights are the shipped demo model") and "640x480" in note
    assert note.endswith("real cameras need a real checkpoint (the authors' pairvpr-vitB.pth, "
                         "see the README)")  # fmt: skip
    assert demo_model_note(f"{demo}+int8|small", np.zeros((240, 320, 3), np.uint8)) == ""
    assert demo_model_note("sha256:0123456789abcdef|vitb", real) == ""


def test_all_keyframes_inside_the_exclusion_window_is_said():
    kf = [SimpleNamespace(stamp=t) for t in (0.0, 5.0, 12.0)]
    ev = SimpleNamespace(exclusion_s=30.0, positives=0)
    (note,) = exclusion_notes(kf, ev)
    assert note.startswith("all 3 keyframes lie within the exclusion window: the bag spans "
                           "12.0 s of keyframes, less than exclude_recent_s = 30 s")  # fmt: skip
    assert exclusion_notes(kf, SimpleNamespace(exclusion_s=10.0, positives=0)) == []
    assert exclusion_notes(kf, SimpleNamespace(exclusion_s=30.0, positives=1)) == []


def test_an_undeclared_lens_is_said_after_three_loops_of_one_sign(monkeypatch):
    """One loop's inliers can fit a k1 by chance: the camera is named only when three loops'
    fit one sign of k1 (a finding of the other sign does not count towards them), once."""
    from pair_vpr_ros.geometry import keyframes
    from pair_vpr_ros.geometry.camera import CameraModel
    from pair_vpr_ros.geometry.relpose import RelativePose
    from pair_vpr_ros.loops.frames import PipelineCounts

    findings = iter([0.035, -0.10, 0.0, -0.12, -0.14, -0.2])
    monkeypatch.setattr(
        keyframes, "relative_pose",
        lambda *a: RelativePose(status="metric", lens_k1=next(findings)),
    )  # fmt: skip
    camera = CameraModel(320, 240, 160.0, 160.0, 160.0, 120.0)
    geometry = keyframes.KeyframeGeometry(None, PipelineCounts())
    said = []
    for _ in range(6):
        geometry.pose(SimpleNamespace(), SimpleNamespace(camera=camera), None)
        said.append(len(geometry.camera_warnings))
    assert said == [0, 0, 0, 0, 1, 1]
    assert geometry.camera_warnings[0].startswith(
        "camera 320x240 (fx 160): 3 loops' inliers fit a radial distortion k1 = -0.120 (median)"
    )
