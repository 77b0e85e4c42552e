"""Several robots' recordings replayed in one process with the fleet exchange between them:
the library behind `pairvpr-fleet-replay` (and `make demo-fleet`).

Each robot gets its own `LoopClosurePipeline` (its own map) over one shared model and its own
`FleetExchange`; a `LocalBus` carries the bytes. The robots' frames are merged by stamp, so a
robot only hears the keyframes other robots made before its own (as live robots would). The
budget and timeouts run on that merged stamp clock.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pair_vpr_ros.errors import ConfigError, OutputError
from pair_vpr_ros.fleet import Faults, FleetConfig, FleetExchange, InterRobotLoop, LocalBus
from pair_vpr_ros.fleet.exchange import CHANNELS
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.identity import Identity, check_name
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame, FrameOutcome
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.model import PairVPRModel
from pair_vpr_ros.offline.bags.sources import FrameCounts, source_frames
from pair_vpr_ros.offline.report.folder import check_writable, naming, writing_outputs

SUMMARY = "fleet_summary.json"


@dataclass
class FleetRobot:
    """One robot of a fleet run: its identity and its frames (a bag or image folder path, or
    Frames in time order). Robot ids must differ within a run."""

    robot: str
    session: str
    source: str | Path | Iterable[Frame]
    topic: str | None = None  # image topic of a bag with several
    pose_topic: str | None = None  # poses attached to keyframes (default: the bag's only one)


@dataclass
class FleetRun:
    """What a fleet run found: inter-robot loops (accepted or not, in decision order), each
    robot's own loop records, and each robot's exchange summary (counts, bytes)."""

    loops: list[InterRobotLoop] = field(default_factory=list)
    robot_loops: dict[str, list[dict]] = field(default_factory=dict)
    exchanges: dict[str, dict] = field(default_factory=dict)
    dropped: int = 0

    def totals(self) -> dict[str, Any]:
        """Fleet-wide bytes: per own keyframe (all messages) and per accepted loop (requests
        and responses of the whole run / accepted inter-robot loops)."""
        ex = self.exchanges.values()
        keyframes = sum(e["keyframes"] for e in ex)
        sent = {ch: sum(e["sent_bytes"].get(ch, 0) for e in ex) for ch in CHANNELS}
        accepted = sum(1 for loop in self.loops if loop.record.accepted)
        scoring = sent["request"] + sent["response"]
        return {
            "keyframes": keyframes, "bytes_sent": sent, "inter_robot_loops": accepted,
            "inter_robot_rejected": len(self.loops) - accepted,
            "descriptor_bytes_per_keyframe": sent["keyframes"] / keyframes if keyframes else 0.0,
            "bytes_per_keyframe": sum(sent.values()) / keyframes if keyframes else 0.0,
            "scoring_bytes_per_accepted_loop": scoring / accepted if accepted else None,
            "dropped_by_bus": self.dropped,
        }  # fmt: skip


def run_fleet(
    robots: list[FleetRobot],
    model: PairVPRModel,
    detector: DetectorConfig | None = None,
    fleet: dict[str, Any] | None = None,
    geometry: GeometryConfig | None = None,
    faults: Faults | None = None,
    batch_size: int = 8,
    progress: bool = False,
) -> FleetRun:
    """Replay `robots` together with the exchange on (`fleet`: FleetConfig options other than
    robot / session, e.g. {"budget": 4, "period_s": 10.0}); `progress`: a tqdm bar."""
    names = [r.robot for r in robots]
    if len(set(names)) != len(names):
        raise ConfigError(f"fleet robots {names} repeat an id: give each robot its own")
    bus, run, streams = LocalBus(faults), FleetRun(), []
    clock = [float("-inf")]
    for r in robots:
        config = FleetConfig(robot=r.robot, session=r.session, **robot_fleet(fleet or {}, r.robot))
        who = Identity(r.robot, r.session)
        pipe = LoopClosurePipeline(model, detector, geometry=geometry, identity=who)
        ex = FleetExchange(pipe, config, bus.sender(r.robot), clock=lambda: clock[0],
                           first_request_id=0)  # fmt: skip
        bus.join(ex)
        run.robot_loops[r.robot] = []
        frames = _frames(r)
        streams.append(_tagged(r.robot, pipe.process_many(frames, batch_size)))
    merged = heapq.merge(*streams, key=lambda item: item[0])
    for stamp, robot, outcome in tqdm(merged, unit="frame", desc="fleet", disable=not progress):
        clock[0] = max(clock[0], stamp)
        ex = bus.exchanges[robot]
        run.robot_loops[robot] += [loop.to_dict() for loop in outcome.reported()]
        ex.on_keyframe(outcome)
        run.loops += bus.deliver()
    for ex in bus.exchanges.values():  # the last period's selected requests
        ex.flush()
    run.loops += bus.deliver(flush=True)
    for robot, ex in bus.exchanges.items():
        ex.expire()
        run.exchanges[robot] = ex.summary()
        ex.pipe.close()
    run.dropped = bus.dropped
    return run


def robot_fleet(fleet: dict[str, Any], robot: str) -> dict[str, Any]:
    """`fleet` for one robot: its peers are the listed ones other than itself (ConfigError
    when the list names only itself: it would listen to no robot)."""
    peers = tuple(fleet.get("peers", ()))
    own = tuple(p for p in peers if p != robot)
    if peers and not own:
        raise ConfigError(
            f"fleet_peers {list(peers)} name only robot {robot!r} itself: list the robots it "
            "listens to, or '' for every robot"
        )
    return {**fleet, "peers": own}


def _frames(robot: FleetRobot) -> Iterable[Frame]:
    if isinstance(robot.source, (str, Path)):
        return source_frames(robot.source, FrameCounts(), robot.topic, pose_topic=robot.pose_topic)
    return robot.source


def _tagged(robot: str, outcomes: Iterator[FrameOutcome]) -> Iterator[tuple]:
    for outcome in outcomes:
        yield outcome.stamp, robot, outcome


def check_fleet_out(out: str | Path, overwrite: bool = False) -> Path:
    """The output folder of a fleet run, checked before any work: OutputError when it holds a
    fleet run's results already (without `overwrite`) or is not a folder."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out} is a file: give a folder for the fleet run's outputs")
    check_writable(out, "--out")
    if (out / SUMMARY).exists() and not overwrite:
        raise OutputError(
            f"--out {out} holds a fleet run already ({SUMMARY}): give another folder or pass "
            "--overwrite"
        )
    return out


def write_fleet_run(run: FleetRun, out: str | Path) -> Path:
    """OUT/inter_robot_loops.json (every decision, `accepted` marks the loops), OUT/<robot>/
    loops.json (each robot's own decisions) and OUT/fleet_summary.json (totals, per robot)."""
    out = Path(out)
    for robot in run.robot_loops:  # names, so no folder is outside `out` or a fixed file
        check_name("robot_id", robot)
    with writing_outputs(out, "fleet run's outputs"):
        out.mkdir(parents=True, exist_ok=True)
        _write_json(out / "inter_robot_loops.json", [loop.to_dict() for loop in run.loops])
        for robot, records in run.robot_loops.items():
            folder = out / robot
            folder.mkdir(exist_ok=True)
            _write_json(folder / "loops.json", records)
        _write_json(out / SUMMARY, {"totals": run.totals(), "robots": run.exchanges})
    return out


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_suffix(".tmp")
    with naming(path, tmp):  # a full disk: named, and no .tmp left behind
        tmp.write_text(json.dumps(data, indent=1, allow_nan=True) + "\n", encoding="utf-8")
    tmp.replace(path)
