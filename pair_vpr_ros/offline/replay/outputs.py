"""Where a replay writes: checked before the bag is read, so a bad destination costs nothing.

A saved place map is never replaced without ``overwrite``, a folder of other files is never
filled with a map, and a folder that cannot be written is found before the first frame. The
map folder's writer lock is taken then and held until the replay saves, so a second replay
(or a node) into the same folder is refused at its start, not after its whole bag.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError, OutputError, os_reason
from pair_vpr_ros.place_map.files import LOCK_NAME, DirLock
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, read_manifest


class MapFolder:
    """The replay's map folder, its writer lock held until `release` (before the save, which
    takes its own); a folder made for it and still empty is removed again then."""

    def __init__(self, path: Path) -> None:
        made = [path, *path.parents]  # the folders made for it: the first that exists stops it
        self._made = made[: next(i for i, p in enumerate(made) if p.exists())]
        self.path, self._lock = path, None
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(
                f"cannot create the map folder {path} ({os_reason(err)}): give another --map-dir"
            ) from err
        try:
            self._lock = DirLock(path)
        except MapError as err:
            self._remove_if_made()
            if "is open for writing" not in str(err):  # a full disk at its lock file
                raise
            holder = (path / LOCK_NAME).read_text(errors="replace").strip() or "?"
            raise OutputError(
                f"map folder {path} is being written by another process (pid {holder}): wait "
                "until it ends (another replay, or a vpr_node with this map_dir), or give "
                "another --map-dir"
            ) from err

    def release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None
            self._remove_if_made()

    def _remove_if_made(self) -> None:
        if not self._made or [p.name for p in self.path.iterdir()] not in ([], [LOCK_NAME]):
            return
        (self.path / LOCK_NAME).unlink(missing_ok=True)
        for folder in self._made:  # innermost first; one holding anything else stays
            try:
                folder.rmdir()
            except OSError:
                return


def check_map_dir(path: Path, overwrite: bool) -> MapFolder:
    """Refuse to replace a saved map, or to fill a folder of other files, unless `overwrite`;
    -> the folder, its writer lock held: another writer (a replay, a node) is refused now,
    rather than after the run."""
    if path.is_dir() and (path / MANIFEST_NAME).exists() and not overwrite:
        try:
            m = read_manifest(path)
            what = f"{m.count} keyframes, model {m.fingerprint}"
        except MapError:
            what = "damaged"
        raise OutputError(
            f"map folder {path} holds a saved place map ({what}) that this replay would "
            "replace: pass --overwrite to replace it, or --map-dir NEW_FOLDER (to add to a "
            "map, load it in vpr_node and play the bag)"
        )
    if path.is_dir() and not overwrite and not (path / MANIFEST_NAME).exists():
        if any(p.name != LOCK_NAME for p in path.iterdir()):
            raise OutputError(
                f"map folder {path} holds other files and no saved map: give a new or empty "
                "folder (or pass --overwrite to save the map beside them)"
            )
    return MapFolder(path)


def prepare_out(out: Path, write_bag: bool) -> Path:
    """Create ``out``, drop a previous run's plots, clear an earlier replay's bag; -> the bag
    folder ``out/bag``."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create the output folder {out}: {err.strerror}") from err
    for stale in ("pr_curve.png", "trajectory.png"):  # a previous run's plots would mislead
        (out / stale).unlink(missing_ok=True)
    bag_out = out / "bag"
    if write_bag and bag_out.exists():
        if not (bag_out / "metadata.yaml").is_file():
            raise ConfigError(f"{bag_out} exists and is not a bag of an earlier replay: move it")
        shutil.rmtree(bag_out)
    return bag_out
