"""Who recorded a keyframe: its robot and its session (issue 22, "identity everywhere").

Every keyframe, loop record and loop factor names a robot and a session on both sides. Recent
keyframes are excluded (and temporal consistency is checked) only within one robot AND one
session: two sessions or two robots never share a clock, so a keyframe of another robot or
session is a candidate at once, whatever its stamp.

One rule for both names, checked at every entry (parameters, flags, fleet messages, map files,
factor frame ids): 1-64 ASCII letters, digits or ``_``, a robot id starting with a letter. So a
name is a safe path component (no ``/``, never ``.`` or ``..``, and without a ``.`` it cannot
equal an output file's name such as ``loops.json``), a ROS topic token (a robot's score
requests go to ``<fleet_request_topic>/<robot_id>``) and a key in every output (no ``@``, which
tags factor frame ids, no ``,`` or spaces).
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
_SESSION = re.compile(r"[A-Za-z0-9_]{1,64}")
_ROBOT = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,63}")
RULE = "1-64 characters of ASCII letters, digits or '_' (a robot id starts with a letter)"


def name_problem(kind: str, value: object) -> str | None:
    """Why `value` is no valid robot / session name; None if it is. `kind` names the input in
    the message ("robot_id", "owner session", ...); a kind holding "robot" is a robot id."""
    robot = "robot" in kind
    if not isinstance(value, str) or not (_ROBOT if robot else _SESSION).fullmatch(value):
        return (
            f"{kind} {value!r} must be {RULE}: it names folders, a ROS topic and pose-graph "
            f"keys, e.g. {'robot1' if robot else '20261125T093000Z'}"
        )
    return None


def check_name(kind: str, value: object) -> str:
    """`value` when it is a valid robot / session name, else ConfigError saying why."""
    problem = name_problem(kind, value)
    if problem:
        raise ConfigError(problem)
    return value  # type: ignore[return-value]


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
        check_name("robot_id", self.robot)
        check_name("session_id", self.session)

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
