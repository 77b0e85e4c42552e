"""scripts/train_demo_model.sh: its machine knobs are checked before anything runs (bad-input
matrix: JOBS, STOP_AFTER)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "train_demo_model.sh"


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ({"JOBS": "x"}, "error: JOBS must be a whole number >= 1, got 'x'"),
        ({"JOBS": "0"}, "error: JOBS must be a whole number >= 1, got '0'"),
        ({"JOBS": "2x"}, "error: JOBS must be a whole number >= 1, got '2x'"),
        ({"STOP_AFTER": "stage1"}, "error: STOP_AFTER must be empty or stage2, got 'stage1'"),
    ],
)
def test_bad_knobs_stop_the_recipe_before_it_starts(
    tmp_path: Path, env: dict[str, str], message: str
) -> None:
    out = tmp_path / "run"
    run = subprocess.run(
        ["bash", str(SCRIPT)],
        env={**os.environ, "OUT": str(out), **env},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (run.returncode, run.stderr.strip()) == (2, message)
    assert not out.exists()  # nothing rendered or trained
