"""The package's import rules (docs/ARCHITECTURE.md), read from the source with `ast`.

Only `pair_vpr_ros/ros/` imports rclpy or a ROS interface package. The areas import one way:
core <- offline <- {ros, learn} <- demo (`ALLOWED`); the core is everything outside ros/,
offline/, learn/ and demo/. Imports inside functions count: hiding one does not make it go away.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "pair_vpr_ros"
ROOT = Path(__file__).resolve().parents[2] / PACKAGE
AREAS = ("ros", "offline", "learn", "demo")
ALLOWED = {
    "core": {"core"},
    "offline": {"core", "offline"},
    "ros": {"core", "offline", "ros"},
    "learn": {"core", "offline", "learn"},
    "demo": {"core", "offline", "learn", "demo"},
}
ROS_PREFIXES = ("rclpy", "rcl_", "rosidl", "launch", "ament_", "rmw", "message_filters")
ROS_SUFFIXES = ("_msgs", "_srvs", "_interfaces", "_bridge")


def is_ros(module: str) -> bool:
    """rclpy, rcl_interfaces, std_msgs, std_srvs, launch_ros, cv_bridge, ... (not `rosbags`,
    the ROS-free bag library)."""
    top = module.split(".")[0]
    return top.startswith(ROS_PREFIXES) or top.endswith(ROS_SUFFIXES)


def area_of(module: str) -> str:
    """`pair_vpr_ros.offline.replay` -> "offline"; `pair_vpr_ros.pipeline` -> "core"."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in AREAS else "core"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path) -> list[tuple[int, str]]:
    """(line, absolute module) for every import statement in `path`, anywhere in the file."""
    module = module_name(path, root)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.append((node.lineno, base))
            if base == PACKAGE or not node.module:  # `from pair_vpr_ros import offline`
                found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def violations(root: Path) -> list[str]:
    """Every import that breaks the rules, as "file:line: what"."""
    out = []
    for path in sorted(root.rglob("*.py")):
        area = area_of(module_name(path, root))
        where = path.relative_to(root.parent)
        for line, target in imports(path, root):
            if is_ros(target) and area != "ros":
                out.append(f"{where}:{line}: imports {target} (only {PACKAGE}/ros/ may)")
            if target.split(".")[0] == PACKAGE and area_of(target) not in ALLOWED[area]:
                out.append(f"{where}:{line}: {area} imports {target} ({area_of(target)})")
    return out


def test_the_package_keeps_its_import_rules():
    assert violations(ROOT) == []


def test_the_rules_catch_each_kind_of_breach(tmp_path):
    pkg = tmp_path / PACKAGE
    files = {
        "__init__.py": "",
        "pipeline.py": "def f():\n    from pair_vpr_ros.learn import evaluate\n",
        "imaging.py": "import rclpy.node\nfrom sensor_msgs.msg import Image\nimport rosbags\n",
        "offline/__init__.py": "",
        "offline/replay.py": "from ..ros import maps\nfrom pair_vpr_ros import learn\n",
        "learn/__init__.py": "",
        "learn/evaluate.py": "from pair_vpr_ros.ros.runtime import load_model\n",
        "ros/__init__.py": "",
        "ros/node.py": "import rclpy\nfrom pair_vpr_ros.offline import build_map\n",
        "demo/__init__.py": "",
        "demo/bag.py": "from std_msgs.msg import String\nimport pair_vpr_ros.learn.datasets\n",
    }
    for name, text in files.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    assert violations(pkg) == [
        f"{PACKAGE}/demo/bag.py:1: imports std_msgs.msg (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/imaging.py:1: imports rclpy.node (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/imaging.py:2: imports sensor_msgs.msg (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/learn/evaluate.py:1: learn imports {PACKAGE}.ros.runtime (ros)",
        f"{PACKAGE}/offline/replay.py:1: offline imports {PACKAGE}.ros (ros)",
        f"{PACKAGE}/offline/replay.py:2: offline imports {PACKAGE}.learn (learn)",
        f"{PACKAGE}/pipeline.py:2: core imports {PACKAGE}.learn (learn)",
    ]
