"""Bad-input matrix, `pairvpr-bag-play`: a bag that is not there or not a bag is one error line
(exit 1), a bad flag value or an unknown topic a usage error (exit 2) naming it; nothing is
played then."""

from __future__ import annotations

import pytest
from bag_fixtures import synthetic_images, write_rosbag2

from pair_vpr_ros.ros.bag_play import main

FLAGS = {
    "rate zero": (["--rate", "0"], "argument --rate: must be a finite number > 0, got '0'"),
    "rate negative": (["--rate=-2"], "argument --rate: must be a finite number > 0, got '-2'"),
    "rate nan": (["--rate", "nan"], "argument --rate: must be a finite number > 0, got 'nan'"),
    "rate text": (["--rate", "fast"], "argument --rate: must be a finite number > 0, got 'fast'"),
    "wait negative": (["--wait=-1"], "argument --wait: must be a finite number >= 0, got '-1'"),
    "wait inf": (["--wait", "inf"], "argument --wait: must be a finite number >= 0, got 'inf'"),
}


@pytest.fixture
def bag(tmp_path):
    images = [(100.0 + i, rgb) for i, rgb in enumerate(synthetic_images(2, size=8))]
    return write_rosbag2(tmp_path / "bag", images, [(100.0, (0.0, 0.0, 0.0))])


@pytest.mark.parametrize("case", list(FLAGS))
def test_bad_flag_is_a_usage_error(bag, capsys, case):
    args, message = FLAGS[case]
    assert main([str(bag), *args]) == 2
    assert message in capsys.readouterr().err


def test_missing_bag(tmp_path, capsys):
    assert main([str(tmp_path / "nope.mcap")]) == 1
    assert capsys.readouterr().err == (
        f"error: bag {tmp_path / 'nope.mcap'} does not exist: give a rosbag2 folder, .mcap or "
        ".db3 file\n"
    )


def test_a_file_that_is_no_bag(tmp_path, capsys):
    path = tmp_path / "notes.mcap"
    path.write_text("not a bag")
    assert main([str(path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: bag {path} cannot be read (") and err.endswith(
        "): is it a rosbag2 bag?\n"
    )


def test_a_topic_the_bag_does_not_have(bag, capsys):
    assert main([str(bag), "--topics", "/cam/image", "/nope"]) == 2
    assert capsys.readouterr().err == (
        f"error: --topics /nope: not in bag {bag} (its topics: /cam/image, /odom)\n"
    )
