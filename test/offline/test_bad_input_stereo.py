"""Stereo inputs in the bad-input matrix: replays of rectified pairs (the right image is the
left one shifted by 5 px: 4 m at f = 100 px, B = 0.2 m) give metric poses; an unrectified,
swapped or mismatched pair, or a right camera_info without a baseline, is a counted skip with
a reason; a right topic not in the bag is a clear error. Core checks of `geometry.stereo`."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from bag_fixtures import TS2, image_msg, textured, write_rosbag2
from test_replay_geometry import CONFIG, INFO, INFO_TOPIC, info_msg

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.geometry.stereo import StereoInputError, check_pair, stereo_baseline
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag

RIGHT, RIGHT_INFO = "/cam/right/image", "/cam/right/camera_info"
SHIFT = 5


@pytest.fixture
def model(tiny_model):
    return tiny_model


def stereo_bag(path, right=lambda img: np.roll(img, -SHIFT, axis=1), p03=-100.0 * 0.2):
    imgs = [textured(s) for s in range(3)]
    stamps, order = [0.0, 1.0, 2.0, 4.0, 5.0], [0, 1, 2, 0, 1]
    images = [(t, imgs[p]) for t, p in zip(stamps, order, strict=True)]
    right_info = info_msg(0.0)
    right_info.p[3] = p03
    extra = [(INFO_TOPIC, INFO, info_msg(0.0), 0.0), (RIGHT_INFO, INFO, right_info, 0.0)]
    extra += [(RIGHT, "sensor_msgs/msg/Image", _image(t, right(imgs[p])), t + 0.001)
              for t, p in zip(stamps, order, strict=True)]  # fmt: skip
    return write_rosbag2(path, images, extra=extra)


def _image(stamp, rgb):
    return image_msg(TS2, stamp, rgb, compressed=False)


def replay(tmp_path, bag, model, **kw):
    kw = {"right_topic": RIGHT, "right_camera_info_topic": RIGHT_INFO, **kw}
    options = ReplayOptions(
        topic="/cam/image", progress=False, overwrite=True, camera_info_topic=INFO_TOPIC, **kw
    )
    return replay_bag(bag, tmp_path / "out", options, model=model, config=CONFIG)


def test_rectified_stereo_pairs_give_metric_poses(tmp_path, model):
    s = replay(tmp_path, stereo_bag(tmp_path / "bag"), model)
    assert s.error is None and s.loops == 2
    assert (s.pipeline_counts["stereo_depth"], s.pipeline_counts["stereo_invalid"]) == (5, 0)
    assert s.pipeline_counts["pose_metric"] == 2


@pytest.mark.parametrize(
    ("right", "p03", "skips"),
    [
        (lambda img: np.roll(img, 6, axis=0), -20.0, {}),  # rows not aligned: unrectified
        (lambda img: np.roll(img, SHIFT, axis=1), -20.0, {}),  # left and right swapped
        (lambda img: img[:100], -20.0, {}),  # another size
        (lambda img: np.roll(img, -SHIFT, axis=1), 0.0,
         {"right camera_info invalid: right camera_info: P[0, 3] = 0 gives no positive baseline; "
          "it must be the RIGHT ": 1}),
    ],
)  # fmt: skip
def test_bad_stereo_pairs_are_counted_skips(tmp_path, model, right, p03, skips):
    s = replay(tmp_path, stereo_bag(tmp_path / "bag", right, p03), model)
    assert s.error is None and s.loops == 2
    assert (s.pipeline_counts["stereo_depth"], s.pipeline_counts["stereo_invalid"]) == (0, 5)
    assert s.pipeline_counts["pose_metric"] == 0
    for key, value in skips.items():
        assert s.geometry_skips[key] == value


def test_a_right_topic_not_in_the_bag_is_refused(tmp_path, model):
    bag = stereo_bag(tmp_path / "bag")
    with pytest.raises(BagError, match="--right-topic /nope is not a sensor_msgs/msg/Image"):
        replay(tmp_path, bag, model, right_topic="/nope")


@pytest.mark.parametrize(
    ("info", "message"),
    [
        (SimpleNamespace(), "right camera_info: not a CameraInfo message"),
        (SimpleNamespace(p=[1.0] * 9), "P must hold 12 finite values with fx > 0"),
        (SimpleNamespace(p=[np.nan] + [0.0] * 11), "P must hold 12 finite values"),
        (SimpleNamespace(p=[100.0, 0, 0, 20.0] + [0.0] * 8), "P[0, 3] = 20 gives no positive"),
    ],
)
def test_bad_right_camera_info(info, message):
    with pytest.raises(StereoInputError) as err:
        stereo_baseline(info)
    assert message in str(err.value)


def test_check_pair_messages():
    left = textured(1)
    with pytest.raises(StereoInputError, match="not rectified: matched features are 6.0 px"):
        check_pair(left, np.roll(left, 6, axis=0))
    with pytest.raises(StereoInputError, match="looks swapped"):
        check_pair(left, np.roll(left, 5, axis=1))
    with pytest.raises(StereoInputError, match="sizes differ: left 160x120, right 160x100"):
        check_pair(left, left[:100])
    check_pair(left, np.roll(left, -5, axis=1))  # rectified: no error
