"""Helpers of the replay-report tests: `check_report` (scripts/check_report.py: the report in
headless Chromium) and the detector settings of the revisit world's report (`REVISIT`: top_k 3,
any score accepted: 17 keyframes, 7 loops with the tiny network, 1 true and 6 false)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from pair_vpr_ros.loops.detector import DetectorConfig

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("check_report", ROOT / "scripts/check_report.py")
check_report = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(check_report)

REVISIT = DetectorConfig(
    top_k=3, score_threshold=-1e9, keyframe_max_similarity=1.0,
    exclude_recent_s=30.0, exclude_recent_keyframes=0,
)  # fmt: skip
