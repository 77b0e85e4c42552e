"""`vpr_node`'s openvino_calibration / openvino_calibration_topic: the images of the given bag
or folder reach the model loader; a missing source stops the start before the weights load."""

from __future__ import annotations

import importlib.util

import cv2
import pytest
import torch
from bag_fixtures import synthetic_images

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.offline.bags.calibration import calibration_images
from pair_vpr_ros.ros import node as node_module

HAS_OPENVINO = all(importlib.util.find_spec(m) for m in ("openvino", "nncf"))


def test_missing_calibration_source_stops_the_start_before_the_weights(harness, monkeypatch):
    monkeypatch.setattr(node_module, "load_model", lambda *a, **k: pytest.fail("loaded"))
    with pytest.raises(ConfigError) as err:
        harness(openvino_calibration="/no/such/bag.mcap")
    assert str(err.value).startswith(
        "openvino_calibration '/no/such/bag.mcap' does not exist: set it to a rosbag"
    )


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs the [openvino] extra")
def test_node_calibrates_on_the_folder_it_is_given(harness, monkeypatch, tmp_path, tiny_model):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, bgr in enumerate(synthetic_images(5, size=16, seed=3)):
        cv2.imwrite(str(folder / f"{i}.png"), bgr)
    seen = {}

    def loader(weights, **kwargs):
        seen["images"] = kwargs["openvino_calibration"](tiny_model.config.image_size)
        seen["backend"] = kwargs["backend"]
        return tiny_model

    monkeypatch.setattr(node_module, "load_model", loader)
    harness(backend="openvino", precision="int8", openvino_calibration=str(folder))
    want = calibration_images(folder, tiny_model.config.image_size)
    assert seen["backend"] == "openvino" and want.shape[0] == 5
    assert torch.equal(seen["images"], want)
