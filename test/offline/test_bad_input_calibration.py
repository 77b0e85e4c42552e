"""Bad-input matrix, int8 calibration sources (parameter openvino_calibration, replay
--openvino-calibration): a missing path, an empty folder, too few usable images, corrupt and
huge-claimed images, a bag without the topic, truncated and part-way corrupt bags. An unusable
image is a counted skip; a source that cannot give 2 images is an error saying what, where and
what to do."""

from __future__ import annotations

import importlib.util
import struct
import zlib

import cv2
import pytest
import torch
from bag_fixtures import (
    COMPRESSED,
    TS2,
    corrupt_foxglove,
    image_msg,
    synthetic_images,
    write_foxglove,
    write_rosbag2,
)

from pair_vpr_ros.errors import BagError, ConfigError
from pair_vpr_ros.model import preprocess_batch
from pair_vpr_ros.offline.bags.calibration import calibration_images, calibration_loader
from pair_vpr_ros.offline.bags.sources import FrameCounts

SIZE = 28
KINDS = (
    "a rosbag (folder, .mcap, .db3 or .bag) or an image folder (.png, .jpg, .jpeg, .bmp, .tif, "
    ".tiff, .webp) (or '' for synthetic scenes)"
)
ADVICE = (
    "int8 calibration needs at least 2: give a bag or folder with more readable camera images "
    "(or '' for synthetic scenes)"
)
UNDECODABLE = "OpenCV could not decode the data (corrupt, truncated or not an image)"
TOO_LARGE = (
    "the image is 20000 x 20000 = 400,000,000 pixels, more than the limit of 50,000,000 "
    "(max_image_pixels): skipped; raise the limit if the camera really sends images this large"
)


def folder_of(path, count, seed=0):
    path.mkdir()
    images = synthetic_images(count, size=16, seed=seed)
    for i, rgb in enumerate(images):
        cv2.imwrite(str(path / f"{i:03d}.png"), rgb)
    return path, [img[:, :, ::-1] for img in images]  # written as BGR: read back reversed


def png_claiming(width: int, height: int) -> bytes:
    """A small real PNG whose IHDR (CRC fixed) claims width x height."""
    data = bytearray(cv2.imencode(".png", synthetic_images(1, size=8)[0])[1].tobytes())
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def test_missing_path(tmp_path):
    with pytest.raises(ConfigError) as err:
        calibration_images(tmp_path / "nope", SIZE)
    assert str(err.value) == (
        f"openvino_calibration '{tmp_path / 'nope'}' does not exist: set it to {KINDS}"
    )


def test_missing_path_is_found_before_any_weights_load(tmp_path):
    with pytest.raises(ConfigError, match="^openvino_calibration '.*nope' does not exist"):
        calibration_loader(str(tmp_path / "nope"))


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images here")
    with pytest.raises(ConfigError) as err:
        calibration_images(tmp_path / "empty", SIZE)
    assert str(err.value) == (
        f"openvino_calibration {tmp_path / 'empty'} is a folder with neither images nor a "
        f"rosbag2 (metadata.yaml or a .mcap/.db3 file) in it: set it to {KINDS}"
    )


def test_folder_with_one_image(tmp_path):
    folder, _ = folder_of(tmp_path / "one", 1)
    with pytest.raises(ConfigError) as err:
        calibration_images(folder, SIZE)
    assert str(err.value) == (
        f"openvino_calibration: 1 usable image(s) of 1 picked from folder {folder}; {ADVICE}"
    )


def test_corrupt_image_is_skipped_and_counted(tmp_path):
    folder, images = folder_of(tmp_path / "imgs", 3)
    (folder / "001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    counts = FrameCounts()
    got = calibration_images(folder, SIZE, counts=counts)
    assert torch.equal(got, preprocess_batch([images[0], images[2]], SIZE))
    assert (counts.frames, counts.skipped) == (3, 1)
    assert counts.first_error == f"image file {folder / '001.png'}: {UNDECODABLE}"


def test_too_few_usable_after_skips_says_why(tmp_path):
    folder, _ = folder_of(tmp_path / "imgs", 2)
    (folder / "000.png").write_bytes(b"")
    with pytest.raises(ConfigError) as err:
        calibration_images(folder, SIZE)
    assert str(err.value) == (
        f"openvino_calibration: 1 usable image(s) of 2 picked from folder {folder} (image file "
        f"{folder / '000.png'}: data is empty); {ADVICE}"
    )


def test_huge_claimed_png_is_skipped_before_decoding(tmp_path):
    folder, images = folder_of(tmp_path / "imgs", 3)
    (folder / "002.png").write_bytes(png_claiming(20000, 20000))
    counts = FrameCounts()
    got = calibration_images(folder, SIZE, counts=counts)
    assert torch.equal(got, preprocess_batch(images[:2], SIZE))
    assert counts.first_error == f"image file {folder / '002.png'}: {TOO_LARGE}"


def test_max_image_pixels_applies(tmp_path):
    folder, _ = folder_of(tmp_path / "imgs", 3)
    counts = FrameCounts()
    with pytest.raises(ConfigError, match=r"^openvino_calibration: 0 usable image\(s\) of 3 "):
        calibration_images(folder, SIZE, max_pixels=100, counts=counts)
    assert counts.skipped == 3 and "16 x 16 = 256 pixels, more than the limit of 100" in (
        counts.first_error
    )


def test_bag_without_the_topic(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", [(1.0, synthetic_images(1)[0])])
    with pytest.raises(BagError) as err:
        calibration_images(bag, SIZE, topic="/nope")
    assert str(err.value) == (
        f"topic /nope is not an image topic of bag {bag}; image topics: /cam/image "
        "(sensor_msgs/msg/Image)"
    )


def test_bag_without_image_topics(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", [], [(1.0, (0.0, 0.0, 0.0))])
    with pytest.raises(BagError) as err:
        calibration_images(bag, SIZE)
    assert str(err.value) == (
        f"bag {bag} has no sensor_msgs/msg/Image or CompressedImage topic (topics: /odom "
        "(nav_msgs/msg/Odometry))"
    )


def test_bag_with_several_image_topics_names_the_parameter(tmp_path):
    rgb = synthetic_images(1)[0]
    extra = [("/other", COMPRESSED, image_msg(TS2, 2.0, rgb, True), 2.0)]
    bag = write_rosbag2(tmp_path / "bag", [(1.0, rgb)], extra=extra)
    with pytest.raises(BagError) as err:
        calibration_images(bag, SIZE)
    assert str(err.value) == (
        f"bag {bag} has 2 image topics: /cam/image (sensor_msgs/msg/Image), /other "
        "(sensor_msgs/msg/CompressedImage); choose one with openvino_calibration_topic (replay: "
        "--openvino-calibration-topic)"
    )


def test_truncated_bag(tmp_path):
    full = write_foxglove(tmp_path / "full.mcap", list(enumerate(synthetic_images(4))))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    with pytest.raises(BagError) as err:
        calibration_images(cut, SIZE)
    assert str(err.value).startswith(f"cannot open bag {cut}: File end magic is invalid.")
    assert str(err.value).endswith(
        "(the MCAP file is truncated or was never closed (recording interrupted?); the MCAP "
        "CLI's `mcap recover` can rebuild it)"
    )


def test_bag_corrupt_part_way_keeps_the_images_before(tmp_path):
    images = synthetic_images(30, size=32, seed=1)
    bag = corrupt_foxglove(tmp_path / "c.mcap", [(float(i), rgb) for i, rgb in enumerate(images)])
    counts = FrameCounts()
    got = calibration_images(bag, SIZE, count=30, counts=counts)
    assert 2 <= got.shape[0] == counts.frames < 30
    assert torch.equal(got, preprocess_batch(images[: got.shape[0]], SIZE))
    assert counts.error.startswith(
        f"reading /cam/image/compressed of bag {bag} stopped at image message {counts.frames} "
    )


def test_bad_messages_are_skipped_and_counted(tmp_path):
    images = synthetic_images(3, size=16, seed=2)
    broken = image_msg(TS2, 1.0, images[1], False, encoding="rgb8", step=1)
    bag = write_rosbag2(
        tmp_path / "bag", [(0.0, images[0]), (2.0, images[2])],
        extra=[("/cam/image", "sensor_msgs/msg/Image", broken, 1.0)],
    )  # fmt: skip
    counts = FrameCounts()
    got = calibration_images(bag, SIZE, counts=counts)
    assert torch.equal(got, preprocess_batch([images[0], images[2]], SIZE))
    assert (counts.frames, counts.skipped) == (3, 1)
    assert counts.first_error.startswith("message 1: ")


# ---- pairvpr-bag-replay: the error line, before the replay starts


def replay(tmp_path, *extra: str) -> int:
    from pair_vpr_ros.offline.replay.cli import main

    bag = tmp_path / "bag"
    if not bag.exists():
        write_rosbag2(bag, [(float(i), rgb) for i, rgb in enumerate(synthetic_images(2))])
    out = ["--out", str(tmp_path / "out"), "--quiet"]
    return main([str(bag), "--weights", "random-tiny", *out, *extra])


@pytest.mark.parametrize("how", ["flag", "params file"])
def test_replay_missing_calibration_source(tmp_path, capsys, how):
    missing = tmp_path / "no_such_bag"
    extra = ["--openvino-calibration", str(missing)]
    if how == "params file":
        params = tmp_path / "p.yaml"
        params.write_text(f"/**:\n  ros__parameters:\n    openvino_calibration: {missing}\n")
        extra = ["--params-file", str(params)]
    assert replay(tmp_path, *extra) == 1
    assert (
        capsys.readouterr().err == f"error: openvino_calibration '{missing}' does not exist: "
        f"set it to {KINDS}\n"
    )
    assert not (tmp_path / "out" / "summary.json").exists()  # refused before the replay


@pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("openvino", "nncf")),
    reason="needs the [openvino] extra",
)
def test_replay_calibration_bag_without_the_topic(tmp_path, capsys):
    calib = write_rosbag2(tmp_path / "calib", [(1.0, synthetic_images(1)[0])])
    extra = ["--openvino-calibration", str(calib), "--openvino-calibration-topic", "/nope"]
    extra += ["--backend", "openvino", "--precision", "int8", "--openvino-cache-dir", "none"]
    assert replay(tmp_path, *extra) == 1
    assert capsys.readouterr().err == (
        f"error: topic /nope is not an image topic of bag {calib}; image topics: /cam/image "
        "(sensor_msgs/msg/Image)\n"
    )
