"""Prior maps: saved place maps opened read-only at start and searched with the live map.

vpr_node's `prior_map_dirs` and the replay's `--prior-map DIR` open them here, before any frame:
every folder must hold a saved map of the running model (same fingerprint, descriptor size and
dense-token shape), no folder may be given twice, and none may hold keyframes of the live robot
and session (a session id names one recording: reusing it would join two unrelated trajectories
under one pose-graph key and exclude their keyframes from each other by stamp). The pipeline
searches them with `map_search.MapSearch` and refuses to save its live map into any of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.identity import LEGACY_SESSION, Identity
from pair_vpr_ros.place_map import PlaceMap


@dataclass
class PriorMaps:
    """The opened prior maps (by the order given) and what to log about them."""

    maps: list[PlaceMap] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def directories(self) -> list[Path]:
        return [m.directory for m in self.maps if m.directory is not None]

    def summary(self) -> list[dict]:
        """Per map: its folder, keyframes and keyframes per robot/session."""
        return [
            {"dir": str(m.directory), "keyframes": len(m), "sessions": sessions_of(m)}
            for m in self.maps
        ]

    def close(self) -> None:
        for place_map in self.maps:
            place_map.close()


def sessions_of(place_map: PlaceMap) -> dict[str, int]:
    """{"robot/session": keyframes} of a map."""
    out: dict[str, int] = {}
    for meta in place_map.all_meta():
        key = f"{meta.robot}/{meta.session}"
        out[key] = out.get(key, 0) + 1
    return out


def open_prior_maps(
    dirs: Sequence[str | Path],
    fingerprint: str,
    identity: Identity,
    what: str = "prior map",
    save_to: str | Path | None = None,
) -> PriorMaps:
    """Open every folder of `dirs` read-only for a model of `fingerprint` and a live run of
    `identity` that will save its map to `save_to` (None: not known yet) -> `PriorMaps`.
    ConfigError (missing folder, given twice, the live session in it), MapError (not a map,
    damaged, `save_to` is one of them) or MapFingerprintError (another model), naming the
    folder; nothing stays open when one fails."""
    out, seen = PriorMaps(), set()
    try:
        for given in dirs:
            path = prior_folder(given, seen, what, "PlaceMap.save, vpr_node's save_map, a "
                                "replay's map/")  # fmt: skip
            out.maps.append(_open(path, given, fingerprint, identity, what, out.notes))
        if save_to is not None:
            refuse_prior_target(save_to, out.maps)
    except BaseException:
        out.close()
        raise
    return out


def prior_folder(given: str | Path, seen: set[Path], label: str, made_by: str) -> Path:
    """The resolved folder of one prior map, added to ``seen``; ConfigError, starting with
    ``label``, for a folder given twice (as resolved) or missing (``made_by``: what saves one)."""
    path = Path(given).expanduser().resolve()
    if path in seen:
        raise ConfigError(f"{label} {given} is given twice: give each folder once")
    seen.add(path)
    if not path.is_dir():
        raise ConfigError(
            f"{label} {given} does not exist or is not a folder: give the folder of a saved "
            f"place map ({made_by})"
        )
    return path


def _open(
    path: Path, given: str | Path, fingerprint: str, who: Identity, what: str, notes: list[str]
) -> PlaceMap:
    try:
        place_map = PlaceMap.load(
            path, expected_fingerprint=fingerprint, read_only=True,
            legacy_identity=(who.robot, LEGACY_SESSION),
        )  # fmt: skip
    except MapError as err:
        raise type(err)(f"{what} {given} cannot be used: {err}") from err
    if place_map.load_note:
        notes.append(place_map.load_note)
    sessions = sessions_of(place_map)
    count = sessions.get(str(who), 0)
    if count:
        place_map.close()
        raise ConfigError(
            f"{what} {given} holds {count} keyframes of robot {who.robot!r} session "
            f"{who.session!r}, the live robot and session: a session id names one recording, so "
            "give this run a new session_id (or leave it empty for the start time)"
        )
    notes.append(f"{what} {path}: {len(place_map)} keyframes (read-only), {sessions}")
    return place_map


def refuse_prior_target(target: str | Path, priors: Sequence[PlaceMap]) -> None:
    """MapError when `target` (a folder a live map is about to be saved to) is a prior map's."""
    resolved = Path(target).expanduser().resolve()
    for place_map in priors:
        if place_map.directory == resolved:
            raise MapError(
                f"{resolved} is a prior map (loaded read-only): the live map is never saved "
                "into a prior map's folder; save it to another folder"
            )
