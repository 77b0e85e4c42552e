"""sources: bag or image folder -> pipeline frames, with unusable images counted, not raised."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from bag_fixtures import IMAGE, TS2, corrupt_foxglove, image_msg, synthetic_images, write_rosbag2

from pair_vpr_ros.errors import BagError, ConfigError
from pair_vpr_ros.images.encoded import IMAGE_SUFFIXES
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.sources import FrameCounts, bag_frames, folder_images, source_frames


def _write(path: Path, rgb: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), path
    return path


def test_folder_reads_every_suffix_in_name_order_and_counts_unreadable(tmp_path):
    images = synthetic_images(len(IMAGE_SUFFIXES), size=32)
    names = [
        f"f{i}{suffix.upper() if i % 2 else suffix}" for i, suffix in enumerate(IMAGE_SUFFIXES)
    ]
    for name, rgb in zip(names, images, strict=True):
        _write(tmp_path / name, rgb)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "e_broken.png").write_bytes(b"not a png")
    assert [p.name for p in folder_images(tmp_path)] == sorted(["e_broken.png", *names])
    counts = FrameCounts()
    frames = list(source_frames(tmp_path, counts, period=0.5))
    assert (counts.frames, counts.skipped, counts.error) == (8, 1, None)
    assert counts.first_error == (
        f"image file {tmp_path / 'e_broken.png'}: OpenCV could not decode the data (corrupt, "
        "truncated or not an image)"
    )
    assert counts.reasons == {counts.first_error: 1}
    assert [f.frame_id for f in frames] == [Path(n).stem for n in names]
    assert [f.stamp for f in frames] == [0.5 * i for i in range(1, 8)]  # the broken one was 0
    assert frames[0].source == str(tmp_path / names[0]) and frames[0].pose is None
    lossless = [f for f in frames if Path(f.source).suffix.lower() in (".png", ".bmp", ".tif")]
    for frame in lossless:
        np.testing.assert_array_equal(frame.rgb, images[names.index(Path(frame.source).name)])


def test_bag_frames_skip_and_count_bad_messages(tmp_path):
    rgb = synthetic_images(1)[0]
    extra = [
        ("/cam", IMAGE, image_msg(TS2, 5.0, rgb, compressed=False, encoding="nope8"), 5.0),
        ("/cam", IMAGE, image_msg(TS2, 6.0, rgb, compressed=False), 6.0),
        ("/cam", IMAGE, image_msg(TS2, 7.0, rgb, compressed=False, encoding="nope8"), 7.0),
    ]
    bag = write_rosbag2(tmp_path / "bag", [], extra=extra)
    counts = FrameCounts()
    with open_bag(bag) as reader:
        got = list(bag_frames(bag_io.iter_frames(reader, "/cam"), counts, "b"))
    assert [(f.stamp, f.source, bf.index) for f, bf in got] == [(6.0, "b#1", 1)]
    assert (counts.frames, counts.skipped, counts.error) == (3, 2, None)
    assert counts.first_error.startswith("message 0: ") and "nope8" in counts.first_error
    assert sum(counts.reasons.values()) == 2 and len(counts.reasons) == 1


def test_a_bag_failing_part_way(tmp_path):
    images = [(float(i), rgb) for i, rgb in enumerate(synthetic_images(12, size=32))]
    bag = corrupt_foxglove(tmp_path / "c.mcap", images)
    counts = FrameCounts()
    with open_bag(bag) as reader:
        topic = bag_io.choose_image_topic(reader)
        got = list(bag_frames(bag_io.iter_frames(reader, topic), counts, "c"))
    assert 0 < len(got) == counts.frames < 12 and counts.skipped == 0
    assert f"stopped at image message {counts.frames} " in counts.error
    again = FrameCounts()  # the map build gets the frames before it, then the BagError
    frames = source_frames(bag, again)
    assert len([next(frames) for _ in range(len(got))]) == len(got)
    with pytest.raises(BagError, match="stopped at image message"):
        next(frames)
    assert again.error == counts.error


def test_source_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"build_source '' does not exist: set it to a rosbag"):
        source_frames("", FrameCounts())
    with pytest.raises(ConfigError, match="build_source '.*absent' does not exist"):
        source_frames(tmp_path / "absent", FrameCounts())
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="empty is a folder with neither images nor a rosbag2"):
        source_frames(tmp_path / "empty", FrameCounts())  # issue 17 #6: names both kinds
