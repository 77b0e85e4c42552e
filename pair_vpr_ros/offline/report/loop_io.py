"""The loop closures of a ``pairvpr-bag-replay`` run, as ``LoopFactor`` s for the pose graph.

Reads any output of a replay: its ``--out`` folder (``loops.json``), ``loops.json``,
``loops.csv``, or the bag ``--write-bag`` wrote (the ``/loop_closure/factor`` topic; any bag with
that topic works, e.g. one recorded from ``vpr_node``). Only accepted loops with a relative pose
become factors; the others are counted with the reason they have none.
"""

from __future__ import annotations

import csv
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pair_vpr_ros.errors import BagError, PoseGraphError
from pair_vpr_ros.messages.factor import (
    FACTOR_TOPIC,
    FACTOR_TYPE,
    STATUS_CODES,
    LoopFactor,
    factor_from_msg,
    factor_from_record,
)
from pair_vpr_ros.offline.bags.opening import open_bag


@dataclass
class LoopSource:
    """The factors read from one source and what was left out, by reason."""

    path: str
    factors: list[LoopFactor] = field(default_factory=list)
    records: int = 0  # loop records (or factor messages) read
    accepted: int = 0  # accepted loops among them
    left_out: Counter[str] = field(default_factory=Counter)  # reason -> accepted loops left out

    @property
    def scale_free(self) -> int:
        return sum(not f.metric for f in self.factors)

    def line(self) -> str:
        text = f"{len(self.factors)} loops with a relative pose ({self.scale_free} scale-free) "
        text += f"of {self.accepted} accepted in {self.records} records"
        if self.left_out:
            text += ", left out: " + ", ".join(f"{n} {r}" for r, n in self.left_out.items())
        return text


def read_loops(path: str | Path) -> LoopSource:
    """The loops at ``path`` (see the module docstring); ``PoseGraphError`` when it is none of
    those or cannot be read."""
    path = Path(path)
    if path.is_dir() and (path / "loops.json").is_file():
        path = path / "loops.json"
    if not path.exists():
        raise PoseGraphError(
            f"loops {path} do not exist: give a pairvpr-bag-replay --out folder, its loops.json "
            "or loops.csv, or a bag with the loop_closure/factor topic"
        )
    if path.suffix == ".json":
        return _from_records(path, json_records(path))
    if path.suffix == ".csv":
        return _from_records(path, _csv_records(path))
    return _from_bag(path)


def json_records(path: Path) -> list[Any]:
    """A loops.json file -> its list of record dicts (PoseGraphError when it is not one)."""
    try:
        records = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise PoseGraphError(f"cannot read loops {path}: {err}") from err
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise PoseGraphError(f"loops {path} is not a JSON list of loop records (loops.json)")
    return records


def _csv_records(path: Path) -> list[dict[str, Any]]:
    """loops.csv rows as record dicts: numbers parsed, ``accepted`` a bool, the covariance the
    list of its 36 space-separated numbers."""
    try:
        with open(path, newline="", encoding="utf-8") as stream:
            rows = list(csv.DictReader(stream))
    except (OSError, csv.Error, UnicodeDecodeError) as err:
        raise PoseGraphError(f"cannot read loops {path}: {err}") from err
    out = []
    for row in rows:
        record: dict[str, Any] = dict(row)
        record["accepted"] = row.get("accepted") == "True"
        record["covariance"] = [float(v) for v in (row.get("covariance") or "").split()]
        out.append(record)
    return out


def _from_records(path: Path, records: list[dict[str, Any]]) -> LoopSource:
    source = LoopSource(str(path), records=len(records))
    for number, record in enumerate(records, start=1):
        if not record.get("accepted"):
            continue
        source.accepted += 1
        try:
            factor = factor_from_record(record)
        except (KeyError, TypeError, ValueError, OverflowError) as err:
            raise PoseGraphError(
                f"loop record {number} of {path} is not a loop record with a pose: {err!r} "
                "(written by an older replay? rerun pairvpr-bag-replay)"
            ) from err
        if factor is None:
            reason = record.get("pose_reason") or _no_pose(record)
            source.left_out[str(reason).split(" (")[0]] += 1
        else:
            source.factors.append(factor)
    return source


def _no_pose(record: dict[str, Any]) -> str:
    """Why an accepted record gave no factor: a damaged covariance, else no relative pose."""
    cov = record.get("covariance") or ()
    if record.get("pose_status") in STATUS_CODES and len(cov) != 36:
        return f"covariance of {len(cov)} values, not 36"
    return "no relative pose"


def _from_bag(path: Path) -> LoopSource:
    topic = "/" + FACTOR_TOPIC
    source = LoopSource(str(path))
    with open_bag(path) as reader:
        info = reader.topics.get(topic)
        if info is None or info.msgtype != FACTOR_TYPE:
            raise BagError(
                f"bag {path} has no {topic} ({FACTOR_TYPE}) topic: write one with "
                "pairvpr-bag-replay --write-bag, or give the replay's loops.json"
            )
        for connection, _, raw in reader.messages(connections=info.connections):
            source.records += 1
            try:
                factor = factor_from_msg(reader.deserialize(raw, connection.msgtype))
            except Exception as err:  # noqa: BLE001 - one bad message is a counted skip
                source.left_out[f"undecodable message: {err}"] += 1
                continue
            source.accepted += 1
            source.factors.append(factor)
    return source
