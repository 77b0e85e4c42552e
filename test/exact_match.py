"""Detector settings under which a tiny random network finds loops deterministically.

Random-init descriptors are nearly collinear (cosine ~0.9999 between any two images), so tests
make revisits exact repeats of earlier images and let only those through: the global floor passes
only identical descriptors, top-1 re-ranks just that candidate, any pair score is accepted, and
short exclusion windows suit sequences of a few frames at 1 s spacing.
"""

from __future__ import annotations

EXACT_MATCH = dict(
    global_floor=0.99999,
    score_threshold=-1e6,
    keyframe_max_similarity=0.99999,
    exclude_recent_s=2.5,
    exclude_recent_keyframes=1,
    top_k=1,
    # exact repeats with a metric pose are represented keyframes under map_growth "places" (not
    # stored); these tests count stored keyframes, test_growth.py tests the policy
    map_growth="all",
)
