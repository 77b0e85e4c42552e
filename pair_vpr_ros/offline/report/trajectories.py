"""Trajectory files and errors through the ``evo`` library: TUM files, ATE and RPE.

A trajectory here is ``stamps [K]`` float64 s with ``poses [K, 7]`` (x, y, z, qx, qy, qz, qw).
Errors compare an estimate with ground truth after associating poses by stamp (nearest within
``max_diff`` s) and an SE(3) Umeyama alignment (rotation + translation, no scale: a metric
odometry's scale error stays in the figure). ATE is the RMSE of the aligned positions; RPE the
RMSE of the translation error over stretches of ``rpe_delta_m`` metres of travel.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.report.folder import naming


@dataclass(frozen=True)
class Trajectory:
    """``stamps [K]`` s and ``poses [K, 7]`` (x, y, z, qx, qy, qz, qw), sorted by stamp."""

    stamps: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.stamps)

    def to_evo(self) -> Any:
        from evo.core.trajectory import PoseTrajectory3D

        return PoseTrajectory3D(
            positions_xyz=np.asarray(self.poses[:, :3], dtype=np.float64),
            orientations_quat_wxyz=np.asarray(self.poses[:, [6, 3, 4, 5]], dtype=np.float64),
            timestamps=np.asarray(self.stamps, dtype=np.float64),
        )

    @classmethod
    def from_evo(cls, traj: Any) -> Trajectory:
        wxyz = traj.orientations_quat_wxyz
        poses = np.concatenate([traj.positions_xyz, wxyz[:, 1:], wxyz[:, :1]], axis=1)
        return cls(np.asarray(traj.timestamps, dtype=np.float64), poses)


@dataclass(frozen=True)
class TrajectoryErrors:
    """ATE / RPE of one estimate against ground truth (metres)."""

    ate_rmse: float
    ate_mean: float
    ate_max: float
    rpe_rmse: float | None  # None when the path is shorter than rpe_delta_m
    rpe_delta_m: float
    matched: int  # poses associated with ground truth

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def write_tum(path: str | Path, trajectory: Trajectory) -> Path:
    """TUM text file: ``stamp x y z qx qy qz qw`` per line."""
    from evo.tools import file_interface

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with naming(path):  # a full disk: the file named in the error
        file_interface.write_tum_trajectory_file(path, trajectory.to_evo())
    return path


def read_tum(path: str | Path) -> Trajectory:
    """The trajectory of a TUM text file."""
    from evo.tools import file_interface

    return Trajectory.from_evo(file_interface.read_tum_trajectory_file(Path(path)))


def _associate(estimate: Trajectory, truth: Trajectory, max_diff: float) -> tuple[Any, Any]:
    """evo trajectories (truth, estimate) of the poses within ``max_diff`` s of each other."""
    from evo.core import sync

    if len(estimate) < 3 or len(truth) < 3:
        raise PoseGraphError(
            f"need at least 3 poses in each trajectory, got {len(estimate)} and {len(truth)}"
        )
    clock = "are both stamped on the same clock?"
    try:
        ref, est = sync.associate_trajectories(
            truth.to_evo(), estimate.to_evo(), max_diff=max_diff
        )
    except sync.SyncException as err:
        raise PoseGraphError(
            f"no pose of the estimate lies within {max_diff} s of a ground-truth pose "
            f"({estimate.stamps[0]:.3f}-{estimate.stamps[-1]:.3f} s vs "
            f"{truth.stamps[0]:.3f}-{truth.stamps[-1]:.3f} s): {clock}"
        ) from err
    if ref.num_poses < 3:
        raise PoseGraphError(
            f"only {ref.num_poses} poses of the estimate lie within {max_diff} s of a "
            f"ground-truth pose: {clock}"
        )
    return ref, copy.deepcopy(est)


def reference_alignment(
    estimate: Trajectory, truth: Trajectory, max_diff: float = 0.05
) -> np.ndarray:
    """``[4, 4]`` SE(3) (Umeyama, no scale) that moves ``estimate`` onto ``truth``: applied to
    every trajectory of a pose graph, it checks they all share the estimate's frame."""
    ref, est = _associate(estimate, truth, max_diff)
    rotation, translation, _ = est.align(ref, correct_scale=False)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, translation
    return out


def trajectory_errors(
    estimate: Trajectory,
    truth: Trajectory,
    max_diff: float = 0.05,
    rpe_delta_m: float = 10.0,
    alignment: np.ndarray | None = None,
) -> TrajectoryErrors:
    """ATE and RPE of ``estimate`` against ``truth`` (see the module docstring); with
    ``alignment`` (``[4, 4]``) the estimate is moved by it instead of aligned on its own."""
    from evo.core import metrics
    from evo.core.units import Unit

    ref, est = _associate(estimate, truth, max_diff)
    if alignment is None:
        est.align(ref, correct_scale=False)
    else:
        est.transform(np.asarray(alignment, dtype=np.float64))
    ate = metrics.APE(metrics.PoseRelation.translation_part)
    ate.process_data((ref, est))
    stats = ate.get_all_statistics()
    rpe_rmse = None
    if ref.path_length > rpe_delta_m:
        rpe = metrics.RPE(
            metrics.PoseRelation.translation_part, delta=rpe_delta_m, delta_unit=Unit.meters,
            all_pairs=True,
        )  # fmt: skip
        try:
            rpe.process_data((ref, est))
            rpe_rmse = float(rpe.get_statistic(metrics.StatisticsType.rmse))
        except metrics.MetricsException:
            rpe_rmse = None
    return TrajectoryErrors(
        ate_rmse=float(stats["rmse"]), ate_mean=float(stats["mean"]), ate_max=float(stats["max"]),
        rpe_rmse=rpe_rmse, rpe_delta_m=rpe_delta_m, matched=int(ref.num_poses),
    )  # fmt: skip


def plot_trajectories(
    path: str | Path,
    truth: Trajectory | None,
    odometry: Trajectory,
    optimised: Trajectory,
    loops: np.ndarray,
    inliers: np.ndarray,
    title: str = "",
) -> Path:
    """PNG (top view, x/y) of ground truth, odometry and the optimised trajectory, with each loop
    drawn between its two optimised nodes (``loops [L, 2, 3]``): solid when the robust kernel
    agrees with the optimised trajectory (``inliers [L]`` bool), dotted red when it does not
    (the robust kernel has down-weighted it)."""
    from pair_vpr_ros.offline.report.plots import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 7))
    if truth is not None and len(truth):
        ax.plot(truth.poses[:, 0], truth.poses[:, 1], "-", color="0.2", lw=2.2,
                label="ground truth")  # fmt: skip
    ax.plot(odometry.poses[:, 0], odometry.poses[:, 1], "-", color="tab:orange", lw=1.2,
            label="odometry")  # fmt: skip
    ax.plot(optimised.poses[:, 0], optimised.poses[:, 1], "-", color="tab:blue", lw=1.2,
            label="optimised (pose graph)")  # fmt: skip
    for trusted, style, name in ((True, dict(color="tab:green", lw=0.6, alpha=0.6), "loop"),
                                 (False, dict(color="tab:red", lw=0.9, ls=":"),
                                  "loop down-weighted by the kernel")):  # fmt: skip
        chosen = loops[inliers == trusted] if len(loops) else loops
        for k, segment in enumerate(chosen):
            ax.plot(segment[:, 0], segment[:, 1], **style, label=name if k == 0 else None)
    ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_fleet(
    path: str | Path,
    before: dict[Any, Trajectory],
    after: dict[Any, Trajectory],
    truth: dict[Any, Trajectory],
    to_truth: np.ndarray | None,
    loops: np.ndarray,
    inliers: np.ndarray,
    between: np.ndarray,
) -> Path:
    """PNG of several robot-sessions (keys ``(robot, session)``): left their odometry, each in
    its own frame; right the optimised trajectories in the map frame, moved onto the ground
    truth by ``to_truth`` (the first trajectory's alignment, ``[4, 4]``) when given, with the
    loops (``[L, 2, 3]``; ``between [L]``: joins two trajectories; red dotted: outliers)."""
    from pair_vpr_ros.offline.report.plots import _pyplot

    plt = _pyplot()
    move = np.eye(4) if to_truth is None else np.asarray(to_truth)
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.5))
    colours = plt.get_cmap("tab10").colors
    for k, key in enumerate(before):
        name, colour = "/".join(key) or "robot", colours[k % len(colours)]
        if key in truth:
            axes[1].plot(*truth[key].poses[:, :2].T, "-", color="0.75", lw=2.5, zorder=0)
        axes[0].plot(*before[key].poses[:, :2].T, "-", color=colour, lw=1.2, label=name)
        xy = after[key].poses[:, :3] @ move[:3, :3].T + move[:3, 3]
        axes[1].plot(xy[:, 0], xy[:, 1], "-", color=colour, lw=1.2, label=name)
    for segment, trusted, joins in zip(loops, inliers, between, strict=True):
        xy = segment @ move[:3, :3].T + move[:3, 3]
        style = ({"color": "tab:red", "lw": 0.9, "ls": ":"} if not trusted else
                 {"color": "k" if joins else "tab:green", "lw": 0.5, "alpha": 0.5})  # fmt: skip
        axes[1].plot(xy[:, 0], xy[:, 1], **style)
    axes[0].set_title("before: odometry, each robot-session in its own frame", fontsize=10)
    axes[1].set_title("after: one frame (grey: truth, black: loops between robot-sessions, "
                      "red: outliers)", fontsize=9)  # fmt: skip
    for ax in axes:
        ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
