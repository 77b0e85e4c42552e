"""Bad-input matrix, bags: truncated at several points, foreign and garbage storage files, broken
metadata.yaml, non-regular files, wrong topics, undecodable messages, stamps that do not increase
and non-finite poses. Opening or reading gives a BagError with a hint, a message is a counted
skip, stamps and poses are counted and warned about (test_bag_io.py has the basic cases)."""

from __future__ import annotations

import os
import shutil
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest
from bad_input import make_fifo
from bag_fixtures import (
    IMAGE,
    ODOMETRY,
    TS2,
    image_msg,
    synthetic_images,
    write_foxglove,
    write_ros1,
    write_rosbag2,
)

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.reader import (
    bad_poses_warning,
    choose_image_topic,
    iter_frames,
    read_poses,
)
from pair_vpr_ros.offline.bags.sources import FrameCounts, bag_frames

IMAGES = [(100.0 + i, rgb) for i, rgb in enumerate(synthetic_images(6, size=16))]


def _cut(path: Path, fraction: float, name: str) -> Path:
    out = path.parent / name
    out.write_bytes(path.read_bytes()[: max(1, int(path.stat().st_size * fraction))])
    return out


def _mcap(tmp: Path) -> Path:
    return write_foxglove(tmp / "full.mcap", IMAGES, compressed=False, chunk_size=3000)


def _db3(tmp: Path) -> Path:
    return next(write_rosbag2(tmp / "db", IMAGES, storage="sqlite3").glob("*.db3"))


def _foreign_db3(tmp: Path) -> Path:
    with sqlite3.connect(tmp / "foreign.db3") as conn:
        conn.execute("CREATE TABLE notes (text TEXT)")
    conn.close()
    return tmp / "foreign.db3"


def _with_metadata(tmp: Path, content: bytes | None, edit=None) -> Path:
    bag = write_rosbag2(tmp / "bag", IMAGES)
    meta = bag / "metadata.yaml"
    if edit is not None:
        content = edit(meta.read_text()).encode()
    meta.write_bytes(content)
    return bag


def _bytes(tmp: Path, name: str, data: bytes) -> Path:
    (tmp / name).write_bytes(data)
    return tmp / name


def _folder(tmp: Path, *storage: str) -> Path:
    (tmp / "folder").mkdir()
    source = _db3(tmp) if storage else None
    for name in storage:
        shutil.copy(source, tmp / "folder" / name)
    return tmp / "folder"


MCAP_CUT = "File end magic is invalid. (the MCAP file is truncated or was never closed"
DB3_CUT = "database disk image is malformed (the sqlite3 (.db3) file is corrupt, truncated"
ROS1_CUT = "Bag index looks damaged: ('Header could not be read from file.',) (the ROS 1 bag"
METADATA = "(the bag folder's metadata.yaml is damaged; `ros2 bag reindex` can rebuild it)"
RANDOM = np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes()
OPEN_CASES = {
    **{
        f"mcap cut at {f:.0%}": (lambda t, f=f: _cut(_mcap(t), f, "cut.mcap"), MCAP_CUT)
        for f in (0.01, 0.1, 0.5, 0.9, 0.99)
    },
    **{
        f"db3 cut at {f:.0%}": (lambda t, f=f: _cut(_db3(t), f, "cut.db3"), DB3_CUT)
        for f in (0.1, 0.3, 0.5)
    },
    **{
        f"ros1 cut at {f:.0%}": (
            lambda t, f=f: _cut(write_ros1(t / "full.bag", IMAGES), f, "cut.bag"),
            ROS1_CUT,
        )
        for f in (0.01, 0.5, 0.99)
    },
    "foreign db3": (_foreign_db3, "or database missing tables. (the sqlite3 (.db3) file is"),
    "garbage ros1": (lambda t: _bytes(t, "g.bag", RANDOM), "(the file is not a bag)"),
    "ros1 of another version": (
        lambda t: _bytes(t, "v.bag", b"#ROSBAG V1.2\n" + RANDOM),
        "Bag version 102 is not supported. (not a ROS 1 bag (version 2.0))",
    ),
    "metadata empty": (lambda t: _with_metadata(t, b""), f"Invalid bag metadata: {''}"),
    "metadata not yaml": (lambda t: _with_metadata(t, b"{{{"), "Could not load YAML from"),
    "metadata list": (lambda t: _with_metadata(t, b"- 1\n"), METADATA),
    "metadata binary": (lambda t: _with_metadata(t, b"\xff\xfe\x00garbage"), METADATA),
    "metadata without info": (
        lambda t: _with_metadata(t, b"foo: 1\n"),
        f"A metadata key is missing KeyError('rosbag2_bagfile_information'). {METADATA}",
    ),
    "metadata version 99": (
        lambda t: _with_metadata(t, None, lambda m: m.replace("version: 9", "version: 99")),
        "Rosbag2 version 99 not supported; please report issue. (written by a rosbag2 newer",
    ),
    "metadata names a missing file": (
        lambda t: _with_metadata(t, None, lambda m: m.replace(".mcap", "_gone.mcap")),
        "(a storage file that metadata.yaml lists is missing: copy the whole bag folder)",
    ),
    "empty folder": (lambda t: _folder(t), "is a folder without metadata.yaml and with 0 .mcap"),
    "two storage files": (lambda t: _folder(t, "a.db3", "b.db3"), "with 2 .mcap/.db3 files"),
    "folder named .mcap": (
        lambda t: (t / "x.mcap").mkdir() or t / "x.mcap",
        "x.mcap is a folder without metadata.yaml and with 0 .mcap/.db3 files",
    ),
    "device named .bag": (
        lambda t: (t / "zero.bag").symlink_to("/dev/zero") or t / "zero.bag",
        "zero.bag is a character device, not a regular file: reading it could block forever",
    ),
    "metadata.yaml is a folder": (
        lambda t: (
            _with_metadata(t, b"")
            and ((t / "bag" / "metadata.yaml").unlink() or (t / "bag" / "metadata.yaml").mkdir())
            or t / "bag"
        ),
        "metadata.yaml is a folder, not a regular file",
    ),
}


@pytest.mark.parametrize("case", list(OPEN_CASES))
def test_bag_that_cannot_be_opened(tmp_path: Path, case: str) -> None:
    make, message = OPEN_CASES[case]
    path = make(tmp_path)
    with pytest.raises(BagError) as info, open_bag(path):
        pass
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def _opens_without_hanging(path: Path, fifo: Path) -> BagError | None:
    """open_bag(path) in a thread; a reader stuck on the FIFO is released and reported."""
    result: list = []

    def run() -> None:
        try:
            with open_bag(path):
                result.append(None)
        except BagError as err:
            result.append(err)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(10.0)
    if thread.is_alive():  # blocked in open(): give it a writer so the thread can end
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(5.0)
        pytest.fail(f"open_bag({path}) blocked on the FIFO {fifo}")
    return result[0]


@pytest.mark.parametrize("where", ["bare file", "storage in a folder", "metadata.yaml"])
def test_fifo_is_refused_without_hanging(tmp_path: Path, where: str) -> None:
    if where == "bare file":
        path = fifo = make_fifo(tmp_path / "live.mcap")
    elif where == "storage in a folder":
        (tmp_path / "bag").mkdir()
        fifo = make_fifo(tmp_path / "bag" / "live.mcap")
        path = tmp_path / "bag"
    else:
        path = write_rosbag2(tmp_path / "bag", IMAGES)
        (path / "metadata.yaml").unlink()
        fifo = make_fifo(path / "metadata.yaml")
    err = _opens_without_hanging(path, fifo)
    assert err is not None
    assert f"{fifo} is a named pipe (FIFO), not a regular file: reading it could block" in str(err)


# ---- readable bags with bad content


def test_image_topic_that_is_a_pose_topic(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag", IMAGES, [(100.0, (0.0, 0.0, 0.0))])
    with open_bag(bag) as reader, pytest.raises(BagError, match="topic /odom is not an image"):
        choose_image_topic(reader, "/odom")


def test_undecodable_messages_are_counted_skips(tmp_path: Path) -> None:
    """Garbage CDR under an Image connection: each message is a counted skip, never a crash."""
    from rosbags.rosbag2 import Writer

    from pair_vpr_ros.offline.bags.opening import jazzy_typestore

    path = tmp_path / "bag"
    with Writer(path, version=9) as writer:
        conn = writer.add_connection("/cam/image", IMAGE, typestore=jazzy_typestore())
        for i, payload in enumerate([b"", b"\x00\x01\x00\x00" + b"\xff" * 7, RANDOM[:64]]):
            writer.write(conn, (100 + i) * 10**9, payload)
    counts = FrameCounts()
    with open_bag(path) as reader:
        frames = list(bag_frames(iter_frames(reader, "/cam/image"), counts, "bag"))
    assert frames == [] and (counts.frames, counts.skipped) == (3, 3)
    assert all(reason.startswith("cannot deserialise: ") for reason in counts.reasons)
    assert counts.first_error.startswith("message 0: cannot deserialise: ")


STAMP_CASES = {
    "increasing": ([1.0, 2.0, 3.0, 4.0], (0, 0), []),
    "one step back": (
        [1.0, 2.0, 1.5, 3.0],
        (1, 0),
        [
            "1 image stamps of /cam/image go back in time (first at message 2: 1.500 s after "
            "2.000 s): a step back of more than 1 s starts a new session (clock_jumps)"
        ],
    ),  # fmt: skip
    "shuffled": ([3.0, 1.0, 4.0, 2.0], (2, 0), ["2 image stamps of /cam/image go back in time"]),
    "one repeat": ([1.0, 2.0, 2.0, 3.0], (0, 1), ["1 image stamps of /cam/image repeat the"]),
    "all identical": (
        [5.0, 5.0, 5.0, 5.0],
        (0, 3),
        ["all 4 image stamps of /cam/image are identical (5.000 s): no frame can match"],
    ),
}


@pytest.mark.parametrize("case", list(STAMP_CASES))
def test_stamps_that_do_not_increase_are_counted(tmp_path: Path, case: str) -> None:
    stamps, expected, warnings = STAMP_CASES[case]
    # received (log time) 1 s apart, in order; the header stamps are the case's
    extra = [
        ("/cam/image", IMAGE, image_msg(TS2, t, rgb, compressed=False), 10.0 + i)
        for i, (t, rgb) in enumerate(zip(stamps, synthetic_images(4, size=16), strict=True))
    ]
    path = write_rosbag2(tmp_path / "bag", [], extra=extra)
    counts = FrameCounts()
    with open_bag(path) as reader:
        frames = list(bag_frames(iter_frames(reader, "/cam/image"), counts, "bag"))
    assert len(frames) == 4 and (counts.backwards, counts.repeated) == expected
    got = counts.stamp_warnings("/cam/image")
    assert len(got) == len(warnings)
    for text, start in zip(got, warnings, strict=True):
        assert text.startswith(start)


def test_non_finite_poses_in_a_bag_are_skipped_and_counted(tmp_path: Path) -> None:
    poses = [(100.0, (1.0, 0.0, 0.0)), (101.0, (float("nan"), 0.0, 0.0))]
    poses += [(102.0, (3.0, float("inf"), 0.0)), (103.0, (4.0, 0.0, 0.0))]
    path = write_rosbag2(tmp_path / "bag", IMAGES[:4], poses, pose_type=ODOMETRY)
    with open_bag(path) as reader:
        track, error = read_poses(reader, "/odom")
        frames = list(iter_frames(reader, "/cam/image", track, pose_tolerance=0.1))
    assert error is None and len(track) == 2 and track.rejected == 2
    assert [f.pose is not None for f in frames] == [True, False, False, True]
    assert bad_poses_warning(track, "/odom") == (
        "2 poses of /odom hold NaN or infinite values and were skipped (the first at stamp "
        "101.000 s); frames near them have no pose"
    )


def test_pixel_limit_reaches_bag_and_folder_sources(tmp_path: Path) -> None:
    """The node's map build reads bags and image folders with its max_image_pixels."""
    from synthetic_data import write_rgb

    from pair_vpr_ros.offline.bags.sources import source_frames

    bag = write_rosbag2(tmp_path / "bag", IMAGES[:2])
    for i, (_, rgb) in enumerate(IMAGES[:2]):
        write_rgb(tmp_path / "folder" / f"{i}.png", rgb)
    for source in (bag, tmp_path / "folder"):
        counts = FrameCounts()
        assert list(source_frames(source, counts, max_pixels=255)) == []
        assert (counts.frames, counts.skipped) == (2, 2)
        assert "16 x 16 = 256 pixels, more than the limit of 255" in counts.first_error
        assert len(list(source_frames(source, FrameCounts(), max_pixels=256))) == 2
