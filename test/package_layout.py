"""What installing this package lays down, read from setup.py itself (no colcon, no pip).

`setup_arguments()` runs setup.py with `setuptools.setup` replaced by a recorder, so the tests
compare launch files and the README with the very names setup.py installs.
`install_prefix(prefix)` copies the `data_files` under `prefix` as an install would, giving an
ament prefix (`AMENT_PREFIX_PATH=prefix`) whose share folder holds the config and launch files.
"""

from __future__ import annotations

import contextlib
import runpy
import shutil
from pathlib import Path
from typing import Any
from unittest import mock

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "pair_vpr_ros"


def setup_arguments() -> dict[str, Any]:
    """The keyword arguments setup.py passes to `setuptools.setup`."""
    recorded: dict[str, Any] = {}
    with contextlib.chdir(ROOT), mock.patch("setuptools.setup", recorded.update):
        runpy.run_path(str(ROOT / "setup.py"), run_name="__main__")
    return recorded


def console_scripts() -> dict[str, str]:
    """{command: "module:function"} of setup.py's console scripts."""
    entries = setup_arguments()["entry_points"]["console_scripts"]
    return {name.strip(): target.strip() for name, target in (e.split("=") for e in entries)}


def installed_files() -> dict[str, Path]:
    """{path under the install prefix: source file} of setup.py's data_files."""
    out = {}
    for folder, files in setup_arguments()["data_files"]:
        for name in files:
            out[f"{folder}/{Path(name).name}"] = ROOT / name
    return out


def install_prefix(prefix: Path) -> Path:
    """Copy the data files under ``prefix`` (an ament prefix, like colcon's install/<pkg>)."""
    for target, source in installed_files().items():
        (prefix / target).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(source, prefix / target)
    return prefix
