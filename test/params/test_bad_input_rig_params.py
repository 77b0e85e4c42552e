"""vpr_node's rig parameters in a parameter file (issue 49): each camera's mapping under
ros__parameters is its own parameters (declared by the node), not refused as unknown names; a
key no camera parameter has, or a bad extrinsic, is refused with what to do."""

from __future__ import annotations

import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.params.rig import rig_cameras

FILE = """/**:
  ros__parameters:
    cameras: [front, rear]
    base_frame: base_footprint
    front:
      image_topic: /cam_front/image_raw
      camera_to_base: [0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]
    rear:
      {rear}
"""


def test_camera_sections_are_read_past_and_cameras_built_from_their_values(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(FILE.format(rear="depth_topic: /cam_rear/depth"))
    values = read_params_file(path)
    assert values["cameras"] == ("front", "rear") and values["base_frame"] == "base_footprint"
    cams = rig_cameras(["front", "rear"], {"front.camera_to_base": [0, 0, 1.6, 0, 0, 0, 2]})
    assert cams[0].camera_to_base == (0, 0, 1.6, 0, 0, 0, 1.0)  # normalised
    assert (cams[1].image_topic, cams[1].camera_info_topic, cams[1].camera_to_base) == (
        "rear/image", "rear/camera_info", None)  # fmt: skip


@pytest.mark.parametrize(
    ("rear", "message"),
    [
        ("image_topc: /x", "camera 'rear' has unknown parameters ['image_topc']"),
        ("camera_to_base: [1.0, 2.0]", None),  # checked when the node builds the rig
    ],
)
def test_a_camera_key_no_parameter_has_is_refused(tmp_path, rear, message):
    path = tmp_path / "rig.yaml"
    path.write_text(FILE.format(rear=rear))
    if message is None:
        read_params_file(path)
        with pytest.raises(ConfigError, match="parameter rear.camera_to_base must be 7 finite"):
            rig_cameras(["rear"], {"rear.camera_to_base": [1.0, 2.0]})
        return
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        read_params_file(path)
