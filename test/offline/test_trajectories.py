"""TUM files and ATE / RPE through evo."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.report.trajectories import (
    Trajectory,
    plot_trajectories,
    read_tum,
    trajectory_errors,
    write_tum,
)
from pair_vpr_ros.posegraph.transforms import planar_pose7, pose3, pose7


def circle(n: int = 200, radius: float = 20.0) -> Trajectory:
    angle = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    poses = [planar_pose7(radius * math.cos(a), radius * math.sin(a), a + math.pi / 2)
             for a in angle]  # fmt: skip
    return Trajectory(1000.0 + np.arange(n) * 0.1, np.array(poses))


def test_tum_file_round_trip(tmp_path):
    traj = circle()
    path = write_tum(tmp_path / "sub" / "t.tum", traj)
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 8 and float(first[0]) == 1000.0 and float(first[1]) == 20.0
    back = read_tum(path)
    np.testing.assert_allclose(back.stamps, traj.stamps)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)


def test_ate_ignores_a_rigid_offset_and_measures_noise():
    truth = circle()
    moved = gtsam.Pose3(gtsam.Rot3.Rz(0.7), np.array([5.0, -3.0, 1.0]))
    offset = Trajectory(
        truth.stamps, np.array([pose7(moved.compose(pose3(p))) for p in truth.poses])
    )
    errors = trajectory_errors(offset, truth)
    assert errors.ate_rmse == pytest.approx(0.0, abs=1e-9) and errors.matched == 200
    # Alternating +-0.3 m along z: alignment cannot remove it, every pose is 0.3 m off.
    noisy = truth.poses.copy()
    noisy[:, 2] += np.where(np.arange(200) % 2, 0.3, -0.3)
    errors = trajectory_errors(Trajectory(truth.stamps, noisy), truth)
    assert errors.ate_rmse == pytest.approx(0.3, abs=1e-6)
    assert errors.ate_max == pytest.approx(0.3, abs=1e-6)
    # A 10 % scale error: every 10 m of travel comes out 1 m long.
    scaled = truth.poses.copy()
    scaled[:, :3] *= 1.1
    errors = trajectory_errors(Trajectory(truth.stamps, scaled), truth)
    assert 0.85 < errors.rpe_rmse < 1.0 and errors.rpe_delta_m == 10.0  # pairs 9-11 m apart


def test_trajectories_without_common_stamps_are_an_error():
    truth = circle()
    later = Trajectory(truth.stamps + 500.0, truth.poses)
    with pytest.raises(PoseGraphError, match="no pose of the estimate lies within 0.05 s of a "):
        trajectory_errors(later, truth)
    with pytest.raises(PoseGraphError, match="need at least 3 poses in each trajectory, got 2"):
        trajectory_errors(Trajectory(truth.stamps[:2], truth.poses[:2]), truth)


def test_plot_is_written(tmp_path):
    truth = circle()
    loops = np.array([[truth.poses[0, :3], truth.poses[100, :3]]] * 2)
    path = plot_trajectories(tmp_path / "p.png", truth, truth, truth, loops,
                             np.array([True, False]), "title")  # fmt: skip
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
