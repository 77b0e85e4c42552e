"""Who recorded a keyframe: its robot and its session (issue 22, "identity everywhere").

Every keyframe, loop record and loop factor names a robot and a session on both sides. Recent
keyframes are excluded (and temporal consistency is checked) only within one robot AND one
session: two sessions or two robots never share a clock, so a keyframe of another robot or
session is a candidate at once, whatever its stamp.

Names are 1-64 characters of letters, digits, ``_``, ``.`` and ``-``: they name files (one
trajectory per robot-session) and pose-graph keys, so nothing else is allowed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime, timezone

from pair_vpr_ros.errors import ConfigError

DEFAULT_ROBOT = "robot"  # robot_id when the node has no namespace
DEFAULT_SESSION = "default"  # session of a pipeline made without one (tests, library use)
LEGACY_SESSION = "legacy"  # session of the keyframes of a map saved before identities existed
SESSION_FORMAT = "%Y%m%dT%H%M%SZ"  # the default session_id: the start time, UTC
_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
RULE = "1-64 characters of letters, digits, '_', '.' or '-'"


def name_problem(kind: str, value: object) -> str | None:
    """Why `value` is no valid robot / session name (`kind`: "robot_id", ...); None if it is."""
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        return (
            f"{kind} {value!r} must be {RULE} (it names files and pose-graph keys), e.g. "
            f"{'robot1' if 'robot' in kind else '20261125T093000Z'}"
        )
    return None


def robot_from_namespace(namespace: str) -> str:
    """The default robot_id of a node in `namespace`: the namespace without slashes (inner
    ones become '_': "/fleet/r1" -> "fleet_r1"), `DEFAULT_ROBOT` for the root namespace."""
    name = "_".join(part for part in str(namespace).split("/") if part)
    return name[:64] if name else DEFAULT_ROBOT


def session_from_time(when: datetime | None = None) -> str:
    """The default session_id: `when` (default: now) in UTC as YYYYMMDDTHHMMSSZ."""
    when = datetime.now(timezone.utc) if when is None else when.astimezone(timezone.utc)
    return when.strftime(SESSION_FORMAT)


@dataclass(frozen=True)
class Identity:
    """A robot and one of its sessions (validated: ConfigError naming the bad one)."""

    robot: str = DEFAULT_ROBOT
    session: str = DEFAULT_SESSION

    def __post_init__(self) -> None:
        for kind, value in (("robot_id", self.robot), ("session_id", self.session)):
            problem = name_problem(kind, value)
            if problem:
                raise ConfigError(problem)

    def __str__(self) -> str:
        return f"{self.robot}/{self.session}"


def resolve_identity(
    robot_id: str = "", session_id: str = "", namespace: str = "/", now: datetime | None = None
) -> Identity:
    """The identity of a node or a replay: '' robot_id = `robot_from_namespace(namespace)`,
    '' session_id = `session_from_time(now)`; ConfigError for a name that breaks the rule."""
    return Identity(
        robot=robot_id or robot_from_namespace(namespace),
        session=session_id or session_from_time(now),
    )
