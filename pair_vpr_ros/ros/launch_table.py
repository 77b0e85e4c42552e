"""The launch files' arguments and what each gives the nodes, in one ROS-free table.

launch/vpr_node.launch.py and launch/vpr_posegraph.launch.py declare `LAUNCHES[file]`'s
arguments and start the nodes of `node_setups(file, values)`; the live demo (`ros.demo_live`,
`make demo-live`) starts the same nodes from the same table, so the demo and the launch cannot
drift apart (`launch_description` builds their launch descriptions; it alone imports
`launch` / `launch_ros`, when called, so the rest stays ROS-free). Sensor topics go to
`vpr_node` as parameters (a topic given turns that input on; a camera_info or depth topic turns
relative poses on), the image as a remapping of `image`.
'' keeps the parameter file's value.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

PACKAGE = "pair_vpr_ros"
CONFIG = "{config}"  # in a default: the installed share/pair_vpr_ros/config folder


@dataclass(frozen=True)
class Argument:
    name: str
    default: str
    description: str


@dataclass
class NodeSetup:
    """One node as launch_ros starts it: parameter files and dicts in order, remappings."""

    executable: str
    parameters: list[str | dict[str, Any]]
    remappings: list[tuple[str, str]]
    shutdown_on_exit: bool = False
    name: str = field(init=False)

    def __post_init__(self) -> None:
        self.name = self.executable


WEIGHTS = Argument(
    "weights", "", "Pair-VPR checkpoint (.pth); '' = the params_file's weights entry, else "
    "$PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/",
)  # fmt: skip
SENSORS = (
    Argument("image", "image", "sensor_msgs/Image of the (left) colour camera"),
    Argument("depth", "", "sensor_msgs/Image depth aligned with image (16UC1 mm or 32FC1 m); "
             "relative poses on; '' = none"),
    Argument("camera_info", "", "sensor_msgs/CameraInfo of image: intrinsics, relative poses "
             "on; '' = the params_file's camera_* values"),
    Argument("right_image", "", "stereo: rectified right image (depth from StereoSGBM); '' = "
             "none"),
    Argument("right_camera_info", "", "stereo: CameraInfo of the right camera; '' = none"),
    Argument("robot_id", "", "robot of every keyframe and loop; '' = the params_file's"),
    Argument("map_dir", "", "map folder of the save/load/build services; '' = the "
             "params_file's"),
)  # fmt: skip
ODOM = "nav_msgs/Odometry of the robot: keyframe poses for vpr_node"
LAUNCHES: dict[str, tuple[Argument, ...]] = {
    "vpr_node.launch.py": (
        WEIGHTS,
        *SENSORS,
        Argument("odom", "", f"{ODOM}; '' = none"),
        Argument("loop_closure", "/lio_loop/loop_closure_detection",
                 "topic of the [t_current, t_previous] pair (LIO-SAM's by default)"),
        Argument("params_file", f"{CONFIG}/vpr_node.yaml", "vpr_node parameters"),
    ),
    "vpr_posegraph.launch.py": (
        WEIGHTS,
        *SENSORS,
        Argument("odom", "odom", f"{ODOM}, and the odometry the pose graph corrects"),
        Argument("loop_closure", "loop_closure",
                 "base name of vpr_node's outputs; the pose graph reads <it>/factor"),
        Argument("camera_to_base", "", "camera pose in the odometry's child frame, '[x, y, z, "
                 "qx, qy, qz, qw]'; '' = the posegraph_params_file's"),
        Argument("prior_map_dirs", "", "saved maps for both nodes, '[/maps/a, /maps/b]': "
                 "vpr_node searches them, posegraph_node takes their sessions as the map "
                 "frame; '' = each params file's"),
        Argument("params_file", f"{CONFIG}/vpr_node.yaml", "vpr_node parameters"),
        Argument("posegraph_params_file", f"{CONFIG}/posegraph_node.yaml",
                 "posegraph_node parameters"),
    ),
}  # fmt: skip
VPR_PARAMETERS = {  # launch argument -> vpr_node parameter, set only when given
    "weights": "weights",
    "depth": "depth_topic",
    "camera_info": "camera_info_topic",
    "right_image": "right_image_topic",
    "right_camera_info": "right_camera_info_topic",
    "odom": "pose_topic",
    "robot_id": "robot_id",
    "map_dir": "map_dir",
}


def defaults(launch: str, config: str | Path) -> dict[str, str]:
    """Every argument of `launch` at its default; `config`: the installed config folder."""
    return {a.name: a.default.replace(CONFIG, str(config)) for a in LAUNCHES[launch]}


def _yaml_list(name: str, text: str, check, example: str) -> list:
    value = yaml.safe_load(text)
    if not (isinstance(value, list) and check(value)):
        raise ValueError(f"{name}:={text!r} is not a list of {example}")
    return value


def node_setups(launch: str, given: Mapping[str, str]) -> list[NodeSetup]:
    """The nodes `launch` starts for the argument values `given` (every argument; '' = not
    given); ValueError names an argument that cannot be used and how to write it."""
    values = dict(given)
    vpr: dict[str, Any] = {p: values[a] for a, p in VPR_PARAMETERS.items() if values.get(a)}
    if values.get("depth") or values.get("camera_info"):
        vpr["relative_pose"] = True
    loops = values["loop_closure"]
    remap = [("image", values["image"]), ("loop_closure", loops)]
    if launch == "vpr_node.launch.py":
        return [NodeSetup("vpr_node", [values["params_file"], *_dicts(vpr)], remap)]
    graph: list[dict[str, Any]] = [{"loop_topic": loops + "/factor"}]
    if values.get("camera_to_base"):
        pose = _yaml_list(
            "camera_to_base", values["camera_to_base"],
            lambda v: len(v) == 7 and all(type(x) in (int, float) for x in v),
            '7 numbers: give camera_to_base:="[x, y, z, qx, qy, qz, qw]"',
        )  # fmt: skip
        graph.append({"camera_to_base": [float(v) for v in pose]})
    if values.get("prior_map_dirs"):  # both: vpr_node searches them, the graph is anchored there
        vpr["prior_map_dirs"] = _yaml_list(
            "prior_map_dirs", values["prior_map_dirs"],
            lambda v: v and all(isinstance(d, str) and d for d in v),
            "folders: give prior_map_dirs:=\"['/maps/monday', '/maps/r2']\"",
        )  # fmt: skip
        graph.append({"prior_map_dirs": vpr["prior_map_dirs"]})
    # one without the other is no use: a vpr_node that cannot start (no weights) would leave
    # a pose graph waiting for loops forever
    return [
        NodeSetup("vpr_node", [values["params_file"], *_dicts(vpr)], remap, True),
        NodeSetup("posegraph_node", [values["posegraph_params_file"], *graph],
                  [("odom", values["odom"])], True),
    ]  # fmt: skip


def _dicts(parameters: dict[str, Any]) -> list[dict[str, Any]]:
    return [parameters] if parameters else []


def ros_args(setup: NodeSetup, params_dir: Path) -> list[str]:
    """The `--ros-args` launch_ros passes to `setup`'s process: its name, parameter files in
    order (a dict is written to a YAML file in `params_dir`, as launch_ros does), remappings."""
    out = ["--ros-args", "-r", f"__node:={setup.name}"]
    for number, entry in enumerate(setup.parameters):
        if isinstance(entry, dict):
            path = params_dir / f"{setup.name}_{number}.yaml"
            path.write_text(json.dumps({"/**": {"ros__parameters": entry}}, indent=1))
            entry = str(path)
        out += ["--params-file", entry]
    return out + [a for source, target in setup.remappings for a in ("-r", f"{source}:={target}")]


def launch_description(launch: str):
    """The `LaunchDescription` of `launch`: its arguments declared with the installed config
    folder's defaults, then its nodes (`node_setups`) once the values are known."""
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue

    def typed(entry):  # launch_ros reads a plain string as YAML: robot_id:=7 would be a number
        if not isinstance(entry, dict):
            return entry  # a parameter file
        return {k: ParameterValue(v, value_type=str) if isinstance(v, str) else v
                for k, v in entry.items()}  # fmt: skip

    def nodes(context) -> list:
        values = {a.name: LaunchConfiguration(a.name).perform(context) for a in LAUNCHES[launch]}
        return [
            Node(
                package=PACKAGE, executable=setup.executable, name=setup.name, output="screen",
                parameters=[typed(p) for p in setup.parameters], remappings=setup.remappings,
                on_exit=Shutdown(reason=f"{setup.name} exited") if setup.shutdown_on_exit
                else None,
            )
            for setup in node_setups(launch, values)
        ]  # fmt: skip

    given = defaults(launch, Path(get_package_share_directory(PACKAGE)) / "config")
    arguments = [
        DeclareLaunchArgument(a.name, default_value=given[a.name], description=a.description)
        for a in LAUNCHES[launch]
    ]
    return LaunchDescription([*arguments, OpaqueFunction(function=nodes)])
