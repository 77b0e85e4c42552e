"""Optional extras in the tests: a test of an extra skips, with the pip command that installs it,
where the extra is not installed, and fails under CI (CI=true), whose set-up installs them all.

`require("pymilvus")` imports a module for a fixture or a test module; test/conftest.py turns a
`ModuleNotFoundError` of an extra's module (at a test module's import or in a test) into the
same skip, so a test module may import its extra at the top like any package."""

from __future__ import annotations

import importlib
import os
import re
from types import ModuleType

import pytest

# module -> the extra of setup.py that installs it (`make setup` installs every one)
EXTRAS = {
    "pymilvus": "milvus",
    "milvus_lite": "milvus",
    "openvino": "openvino",
    "nncf": "openvino",
    "gtsam": "slam",
    "evo": "slam",
    "pytorch_metric_learning": "train",
    "mkdocs": "docs",
}
_MISSING = re.compile(r"ModuleNotFoundError: No module named '([\w.]+)'")


def in_ci() -> bool:
    return bool(os.environ.get("CI"))


def skip_reason(module: str) -> str | None:
    """Why a test skips when `module` (dotted or not) is missing; None: not an extra's module."""
    extra = EXTRAS.get(module.split(".")[0])
    if extra is None:
        return None
    return f"{module} is not installed: pip install -e '.[{extra}]' (make setup installs it)"


def reason_in(text: str) -> str | None:
    """The skip reason when `text` (a failure's report) is an extra's missing module."""
    found = _MISSING.search(text)
    return skip_reason(found[1]) if found else None


def require(module: str) -> ModuleType:
    """`module`, imported; skip (fail under CI) with the pip command when it is missing."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        reason = skip_reason(err.name or module) or f"{module} is not installed ({err})"
        if in_ci():
            pytest.fail(f"CI: {reason}", pytrace=False)
        pytest.skip(reason, allow_module_level=True)
