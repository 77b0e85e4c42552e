"""The package's shape and import rules (docs/ARCHITECTURE.md), read from the source with `ast`.

- Only `pair_vpr_ros/ros/` imports rclpy or a ROS interface package.
- Each stage imports only from itself and from the stages below it (`RANK`): the shared
  vocabulary at the bottom, then model and images, place_map and geometry, loops, messages,
  fleet and posegraph, params, the weights resolver, and offline / ros / learn / demo on top.
  Inside offline/ the same holds for its jobs (bags < report < report.html < replay,
  posegraph < fleet).
- No import circles between modules, and no module that only re-exports another's names.
- At most 6 top-level modules, 16 modules a folder, 350 lines a module.

Imports inside functions and under `if TYPE_CHECKING` count: hiding one does not make it go away.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "pair_vpr_ros"
ROOT = Path(__file__).resolve().parents[2] / PACKAGE
# Stage -> rank. A module belongs to the longest stage name that prefixes its dotted path
# below the package; a top-level module not named here is shared vocabulary ("base").
RANK = {
    "base": 0,  # errors, types, identity, hashing, cli
    "model": 1,
    "images": 1,
    "place_map": 2,
    "geometry": 2,
    "loops": 3,
    "messages": 4,
    "fleet": 5,
    "posegraph": 5,
    "params": 6,
    "weights": 7,
    "offline.bags": 8.0,
    "offline.report": 8.1,
    "offline.report.html": 8.15,
    "offline.replay": 8.2,
    "offline.posegraph": 8.2,
    "offline.fleet": 8.3,
    "offline.map_cli": 8.4,
    "ros": 9,
    "learn": 9,
    "demo": 10,
}
MAX_TOP_MODULES, MAX_FOLDER_MODULES, MAX_LINES = 6, 16, 350
ROS_PREFIXES = ("rclpy", "rcl_", "rosidl", "launch", "ament_", "rmw", "message_filters")
ROS_SUFFIXES = ("_msgs", "_srvs", "_interfaces", "_bridge")


def is_ros(module: str) -> bool:
    """rclpy, rcl_interfaces, std_msgs, std_srvs, launch_ros, cv_bridge, ... (not `rosbags`,
    the ROS-free bag library)."""
    top = module.split(".")[0]
    return top.startswith(ROS_PREFIXES) or top.endswith(ROS_SUFFIXES)


def stage_of(module: str) -> str:
    """`pair_vpr_ros.offline.replay.cli` -> "offline.replay"; `pair_vpr_ros.errors` -> "base"."""
    rest = module.split(".")[1:]
    for n in range(len(rest), 0, -1):
        if ".".join(rest[:n]) in RANK:
            return ".".join(rest[:n])
    return "base"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path, modules: set[str] = frozenset()) -> list[tuple[int, str]]:
    """(line, absolute module) for every import statement in `path`, anywhere in the file;
    `from a import b` counts as an import of `a.b` where `a.b` is one of `modules`."""
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
            subs = [f"{base}.{a.name}" for a in node.names]
            subs = [s for s in subs if s in modules or base == PACKAGE or not node.module]
            found += [(node.lineno, s) for s in subs] or [(node.lineno, base)]
    return found


def package_modules(root: Path) -> dict[str, Path]:
    return {module_name(p, root): p for p in sorted(root.rglob("*.py"))}


def violations(root: Path) -> list[str]:
    """Every import that breaks the rules, as "file:line: what"."""
    out = []
    mods = package_modules(root)
    for module, path in mods.items():
        stage = stage_of(module)
        where = path.relative_to(root.parent)
        for line, target in imports(path, root, set(mods)):
            if is_ros(target) and stage != "ros":
                out.append(f"{where}:{line}: imports {target} (only {PACKAGE}/ros/ may)")
            if target.split(".")[0] != PACKAGE or target == PACKAGE:
                continue
            other = stage_of(target)
            if other != stage and RANK[other] >= RANK[stage]:
                out.append(f"{where}:{line}: {stage} imports {target} ({other}, not below it)")
    return out


def circles(root: Path) -> list[list[str]]:
    """The import circles between the package's modules (strongly connected components of the
    module graph with more than one module), each sorted."""
    mods = package_modules(root)
    graph = {m: {t for _, t in imports(p, root, set(mods)) if t in mods} for m, p in mods.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(m: str) -> None:  # Tarjan's algorithm
        index[m] = low[m] = len(index)
        stack.append(m)
        for t in graph[m]:
            if t not in index:
                visit(t)
                low[m] = min(low[m], low[t])
            elif t in stack:
                low[m] = min(low[m], index[t])
        if low[m] == index[m]:
            component = []
            while True:
                t = stack.pop()
                component.append(t)
                if t == m:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for m in graph:
        if m not in index:
            visit(m)
    return sorted(found)


def only_reexports(path: Path) -> bool:
    """A module (not a package's __init__) that defines nothing of its own."""
    own = (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Assign, ast.AnnAssign)
    body = ast.parse(path.read_text()).body
    names = [n for n in body if isinstance(n, own)]
    return path.name != "__init__.py" and all(
        isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "__all__" for t in n.targets)
        for n in names
    )


def shape_problems(root: Path) -> list[str]:
    """Top-level modules, modules per folder, lines per module, re-export-only modules."""
    out = []
    top = [p.name for p in root.glob("*.py") if p.name != "__init__.py"]
    if len(top) > MAX_TOP_MODULES:
        out.append(f"{len(top)} top-level modules (at most {MAX_TOP_MODULES}): {sorted(top)}")
    for folder in sorted({root, *(p.parent for p in root.rglob("*.py"))}):
        n = len([p for p in folder.glob("*.py") if p.name != "__init__.py"])
        if n > MAX_FOLDER_MODULES:
            out.append(f"{folder.relative_to(root.parent)}: {n} modules")
    for path in sorted(root.rglob("*.py")):
        lines = len(path.read_text().splitlines())
        if lines > MAX_LINES:
            out.append(f"{path.relative_to(root.parent)}: {lines} lines")
        if only_reexports(path):
            out.append(f"{path.relative_to(root.parent)}: only re-exports")
    return out


def test_the_package_keeps_its_import_rules():
    assert violations(ROOT) == []


def test_the_package_has_no_import_circles():
    assert circles(ROOT) == []


def test_the_package_keeps_its_shape():
    assert shape_problems(ROOT) == []


def test_every_stage_of_the_table_exists():
    folders = {module_name(p, ROOT).partition(".")[2] for p in ROOT.rglob("__init__.py")}
    stages = set(RANK) - {"base", "weights", "offline.map_cli"}
    assert stages <= folders, stages - folders
    assert (ROOT / "weights.py").is_file() and (ROOT / "offline" / "map_cli.py").is_file()


def _write(pkg: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    return pkg


def test_the_rules_catch_each_kind_of_breach(tmp_path):
    pkg = _write(
        tmp_path / PACKAGE,
        {
            "__init__.py": "",
            "errors.py": "from pair_vpr_ros.loops import pipeline\n",
            "loops/__init__.py": "",
            "loops/pipeline.py": "def f():\n    from pair_vpr_ros.learn import evaluate\n",
            "images/__init__.py": "",
            "images/convert.py": "import rclpy.node\nfrom sensor_msgs.msg import Image\n"
            "import rosbags\nfrom pair_vpr_ros.model import network\n",
            "fleet/__init__.py": "",
            "fleet/peers.py": "from pair_vpr_ros.posegraph.graph import PoseGraph\n",
            "offline/__init__.py": "",
            "offline/bags/__init__.py": "",
            "offline/bags/reader.py": "from pair_vpr_ros.offline.replay import run\n",
            "offline/replay/__init__.py": "",
            "offline/replay/run.py": "from ...ros import maps\nfrom pair_vpr_ros import learn\n",
            "learn/__init__.py": "",
            "learn/evaluate.py": "from pair_vpr_ros.ros.runtime import load_model\n",
            "ros/__init__.py": "",
            "ros/node.py": "import rclpy\nfrom pair_vpr_ros.offline.replay import build_map\n",
            "demo/__init__.py": "",
            "demo/bag.py": "from std_msgs.msg import String\nimport pair_vpr_ros.learn.places\n",
        },
    )
    assert violations(pkg) == [
        f"{PACKAGE}/demo/bag.py:1: imports std_msgs.msg (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/errors.py:1: base imports {PACKAGE}.loops.pipeline (loops, not below it)",
        f"{PACKAGE}/fleet/peers.py:1: fleet imports {PACKAGE}.posegraph.graph (posegraph, "
        "not below it)",
        f"{PACKAGE}/images/convert.py:1: imports rclpy.node (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/images/convert.py:2: imports sensor_msgs.msg (only {PACKAGE}/ros/ may)",
        f"{PACKAGE}/images/convert.py:4: images imports {PACKAGE}.model (model, not below it)",
        f"{PACKAGE}/learn/evaluate.py:1: learn imports {PACKAGE}.ros.runtime (ros, not below it)",
        f"{PACKAGE}/loops/pipeline.py:2: loops imports {PACKAGE}.learn.evaluate (learn, not "
        "below it)",
        f"{PACKAGE}/offline/bags/reader.py:1: offline.bags imports {PACKAGE}.offline.replay.run "
        "(offline.replay, not below it)",
        f"{PACKAGE}/offline/replay/run.py:1: offline.replay imports {PACKAGE}.ros (ros, not "
        "below it)",
        f"{PACKAGE}/offline/replay/run.py:2: offline.replay imports {PACKAGE}.learn (learn, not "
        "below it)",
    ]


def test_circles_are_found_however_the_import_is_written(tmp_path):
    pkg = _write(
        tmp_path / PACKAGE,
        {
            "__init__.py": "",
            "a.py": "from pair_vpr_ros import b\n",
            "b.py": "def f():\n    from pair_vpr_ros.c import x\n",
            "c.py": "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n    import pair_vpr_ros.a\n",
            "d.py": "from pair_vpr_ros.e import y\n",
            "e.py": "y = 1\n",
        },
    )
    assert circles(pkg) == [[f"{PACKAGE}.a", f"{PACKAGE}.b", f"{PACKAGE}.c"]]


def test_the_shape_rules_catch_each_kind_of_breach(tmp_path):
    files = {"__init__.py": "", "re.py": "from x import y\n\n__all__ = ['y']\n"}
    files |= {f"m{i}.py": "x = 1\n" for i in range(6)}
    files |= {f"big/m{i}.py": "x = 1\n" for i in range(17)}
    files["long.py"] = "x = 1\n" * 351
    pkg = _write(tmp_path / PACKAGE, files)
    top = sorted(["long.py", "re.py"] + [f"m{i}.py" for i in range(6)])
    assert shape_problems(pkg) == [
        f"8 top-level modules (at most 6): {top}",
        f"{PACKAGE}/big: 17 modules",
        f"{PACKAGE}/long.py: 351 lines",
        f"{PACKAGE}/re.py: only re-exports",
    ]
