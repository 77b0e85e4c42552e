"""The node's map services without ROS: save / load / clear / autosave and background builds."""

from __future__ import annotations

import contextlib
import re
import threading

import cv2
import numpy as np
import pytest
from bag_fixtures import synthetic_images, write_rosbag2
from exact_match import EXACT_MATCH

from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame, PipelineCounts
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.offline.replay.build_map import build_map
from pair_vpr_ros.ros.maps import LiveState, MapControl

EXACT = DetectorConfig(**EXACT_MATCH)


@pytest.fixture
def control(tiny_model):
    logs: list[tuple[str, str]] = []
    ctl = MapControl(
        lambda: LoopClosurePipeline(tiny_model, EXACT), lambda *entry: logs.append(entry)
    )
    ctl.logs = logs
    yield ctl
    ctl.close()


def feed(ctl: MapControl, images, t0: float = 0.0):
    return [ctl.process(Frame(t0 + i, rgb, "cam"))[0] for i, rgb in enumerate(images)]


def image_folder(path, images):
    path.mkdir()
    for i, rgb in enumerate(images):
        cv2.imwrite(str(path / f"img{i:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def test_save_clear_load_round_trip(control, tmp_path):
    assert control.save("") == (
        False,
        "map_dir is not set: ros2 param set /vpr_node map_dir /path/to/map",
    )
    feed(control, synthetic_images(3))
    ok, message = control.save(str(tmp_path / "map"))
    assert ok and message == f"saved 3 keyframes to {tmp_path / 'map'}"
    assert control.autosave(str(tmp_path / "map")) is None  # unchanged since the save
    assert control.clear() == (True, "map cleared (the saved copy is unchanged)")
    assert control.size() == 0
    assert control.load(str(tmp_path / "map")) == (
        True,
        f"loaded 3 keyframes from {tmp_path / 'map'}",
    )
    feed(control, synthetic_images(1, seed=5), t0=10.0)
    assert control.autosave(str(tmp_path / "map")) == (
        True,
        f"saved 4 keyframes to {tmp_path / 'map'}",
    )
    ok, message = control.load(str(tmp_path / "nothing"))
    assert not ok and "nothing" in message


def test_other_threads_read_a_copy_made_on_the_map_thread(control):
    per_keyframe = control.pipeline.place_map.bytes_per_keyframe
    assert control.state == LiveState(0, "mapping", PipelineCounts(), per_keyframe)
    feed(control, synthetic_images(3))
    assert control.state == LiveState(
        3, "mapping", PipelineCounts(encoded=3, keyframes=3), per_keyframe
    )
    assert control.state.counts is not control.pipeline.counts
    control.set_config(EXACT.updated(mode="localization"))
    assert control.state.mode == "localization"


def test_start_up_load_of_a_missing_folder_is_a_fresh_start(control, tmp_path):
    assert control.load_if_present(str(tmp_path / "new")) == (
        True,
        f"no map in {tmp_path / 'new'} yet: starting with an empty map",
    )


def test_build_from_image_folder_replaces_the_live_map(control, tmp_path):
    images = synthetic_images(4) + synthetic_images(1)  # the last image revisits the first
    folder = image_folder(tmp_path / "imgs", images)
    feed(control, synthetic_images(2, seed=9))
    ok, message = control.start_build(str(folder), str(tmp_path / "map"), EXACT)
    assert ok and message.startswith(f"building a map from {folder} into {tmp_path / 'map'}")
    assert control.wait_build(60.0)
    expected = re.escape(f"done: 5 keyframes from 5 images of {folder} (0 skipped, 1 loops, ")
    assert re.fullmatch(expected + r"\d+\.\d s\)", control.build_state)
    assert control.size() == 5
    metas = control.call(lambda: control.pipeline.place_map.all_meta())
    assert [m.stamp for m in metas] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert metas[0].frame_id == "img000" and metas[0].source == str(folder / "img000.png")
    assert control.logs[-1][0] == "info"


def test_build_from_bag_attaches_poses(control, tmp_path):
    images = [(10.0 + i, rgb) for i, rgb in enumerate(synthetic_images(3))]
    poses = [(10.0 + i, (float(i), 2.0, 0.0)) for i in range(3)]
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    assert control.start_build(str(bag), str(tmp_path / "map"), EXACT)[0]
    assert control.wait_build(60.0) and control.build_state.startswith("done: 3 keyframes")
    meta = control.call(lambda: control.pipeline.place_map.meta(2))
    assert (meta.stamp, meta.pose) == (12.0, (2.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0))


def test_build_into_the_folder_the_live_map_holds(control, tmp_path):
    feed(control, synthetic_images(2, seed=3))
    assert control.save(str(tmp_path / "map"))[0]  # the live map now locks tmp/map
    folder = image_folder(tmp_path / "imgs", synthetic_images(3))
    assert control.start_build(str(folder), str(tmp_path / "map"), EXACT)[0]
    assert control.wait_build(60.0) and control.build_state.startswith("done: 3 keyframes")
    assert control.size() == 3 and control.load(str(tmp_path / "map"))[1].startswith("loaded 3")


def test_second_build_is_refused_while_one_runs(tiny_model, tmp_path):
    folder = image_folder(tmp_path / "imgs", synthetic_images(2))
    release = threading.Event()

    @contextlib.contextmanager
    def held():  # holds the build (not the map thread) until released
        if threading.current_thread().name == "vpr_build":
            release.wait(30.0)
        yield

    control = MapControl(lambda: LoopClosurePipeline(tiny_model, EXACT), print, held)
    assert control.start_build(str(folder), str(tmp_path / "map"), EXACT)[0]
    ok, message = control.start_build(str(folder), str(tmp_path / "map"), EXACT)
    assert not ok
    assert message == (
        f"a map build is running already (building from {folder}): wait for it to finish"
    )
    release.set()
    assert control.wait_build(60.0) and control.build_state.startswith("done: 2 keyframes")
    control.close()


def test_failed_build_keeps_the_live_map(control, tmp_path):
    feed(control, synthetic_images(2))
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "a.png").write_bytes(b"not a png")
    assert control.start_build(str(folder), str(tmp_path / "map"), EXACT)[0]
    assert control.wait_build(60.0)
    assert control.build_state == (
        f"failed: build_source {folder} gave no usable image (first error: "
        f"image file {folder / 'a.png'}: OpenCV could not decode the data (corrupt, truncated or "
        "not an image))"
    )
    assert control.logs[-1][0] == "error" and control.size() == 2
    ok, message = control.start_build(str(tmp_path / "absent"), str(tmp_path / "map"), EXACT)
    assert not ok and message.startswith(f"build_source '{tmp_path / 'absent'}' does not exist")


def test_build_stops_when_asked(tiny_model, tmp_path):
    folder = image_folder(tmp_path / "imgs", synthetic_images(4))
    stop = threading.Event()
    stop.set()
    pipe, result = build_map(tiny_model, EXACT, folder, stop=stop, batch_size=1)
    pipe.close()
    assert result.cancelled and result.frames == 1


def test_folder_images_are_read_in_name_order(tiny_model, tmp_path):
    images = synthetic_images(3)
    folder = image_folder(tmp_path / "imgs", images)
    (folder / "notes.txt").write_text("ignored")
    pipe, result = build_map(tiny_model, EXACT, folder, image_period=0.5)
    stamps = [m.stamp for m in pipe.place_map.all_meta()]
    pipe.close()
    assert (result.frames, result.skipped, result.keyframes, stamps) == (3, 0, 3, [0.0, 0.5, 1.0])
    assert np.array_equal(
        cv2.cvtColor(cv2.imread(str(folder / "img001.png")), cv2.COLOR_BGR2RGB), images[1]
    )


def test_build_checks_both_ends_before_it_starts(control, tmp_path):
    # Issue 17 #5 and #6 (bad-input matrix of build_source and map_dir for build_map): answered
    # at once, nothing started, the live map and the file untouched.
    good = image_folder(tmp_path / "imgs", synthetic_images(2))
    (tmp_path / "empty").mkdir()
    a_file = tmp_path / "map.txt"
    a_file.write_text("not a map")
    hint = "ros2 param set /vpr_node map_dir /path/to/map"
    kinds = (
        "a rosbag (folder, .mcap, .db3 or .bag) or an image folder (.png, .jpg, .jpeg, .bmp, "
        ".tif, .tiff, .webp)"
    )
    source_hint = "(ros2 param set /vpr_node build_source /path/to/bag_or_image_folder)"
    cases = {
        (str(good), str(a_file)): f"map_dir {a_file} is a file, not a folder: {hint}",
        (str(good), str(a_file / "sub")): (
            f"map_dir {a_file / 'sub'} cannot be written ({a_file} is not a writable folder): "
            f"{hint}"
        ),
        (str(good), ""): f"map_dir is not set: {hint}",
        (str(tmp_path / "empty"), str(tmp_path / "map")): (
            f"build_source {tmp_path / 'empty'} is a folder with neither images nor a rosbag2 "
            f"(metadata.yaml or a .mcap/.db3 file) in it: set it to {kinds} {source_hint}"
        ),
        ("", str(tmp_path / "map")): (
            f"build_source '' does not exist: set it to {kinds} {source_hint}"
        ),
    }
    for (source, map_dir), message in cases.items():
        assert control.start_build(source, map_dir, EXACT) == (False, message)
        assert control.build.state == "idle" and control.build_state == "idle"
    assert a_file.read_text() == "not a map" and not (tmp_path / "map").exists()


def test_a_failed_build_stays_reported_until_one_succeeds(control, tmp_path):
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "a.png").write_bytes(b"not a png")
    assert control.start_build(str(folder), str(tmp_path / "map"), EXACT)[0]
    assert control.wait_build(60.0)
    failed = control.build.to_dict()
    assert (failed["state"], failed["source"], failed["frames_read"]) == ("failed", str(folder), 1)
    assert failed["error"].startswith(f"building a map from {folder} into {tmp_path / 'map'} ")
    good = image_folder(tmp_path / "imgs", synthetic_images(2))
    assert control.start_build(str(good), str(tmp_path / "map"), EXACT)[0]
    assert control.build.error == failed["error"]  # still an error while the next one runs
    assert control.wait_build(60.0)
    done = control.build.to_dict()
    assert done == dict(
        state="done", source=str(good), map_dir=str(tmp_path / "map"),
        detail=done["detail"], error="", frames_read=2,
    )  # fmt: skip
    assert done["detail"].startswith("2 keyframes from 2 images")
