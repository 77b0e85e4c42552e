"""Where a replay writes: checked before the bag is read, so a bad destination costs nothing.

A saved place map is never replaced without ``overwrite``, a folder of other files is never
filled with a map, and a folder that cannot be written is found before the first frame.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError, OutputError
from pair_vpr_ros.place_map.files import LOCK_NAME, DirLock
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, read_manifest


def check_map_dir(path: Path, overwrite: bool) -> None:
    """Refuse to replace a saved map, or to fill a folder of other files, unless `overwrite`;
    a map another program has open for writing is refused now rather than after the run."""
    if not path.is_dir() or overwrite and not (path / MANIFEST_NAME).exists():
        return
    if (path / MANIFEST_NAME).exists():
        if not overwrite:
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
        DirLock(path).release()  # MapError when another PlaceMap writes there
    elif any(p.name != LOCK_NAME for p in path.iterdir()):
        raise OutputError(
            f"map folder {path} holds other files and no saved map: give a new or empty folder "
            "(or pass --overwrite to save the map beside them)"
        )


def prepare_out(out: Path, write_bag: bool) -> Path:
    """Create ``out``, drop a previous run's plots, clear an earlier replay's bag; -> the bag
    folder ``out/bag``."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create the output folder {out}: {err.strerror}") from err
    # a previous run's plots and suggested parameters would mislead
    for stale in ("pr_curve.png", "trajectory.png", "suggested_params.yaml"):
        (out / stale).unlink(missing_ok=True)
    bag_out = out / "bag"
    if write_bag and bag_out.exists():
        if not (bag_out / "metadata.yaml").is_file():
            raise ConfigError(f"{bag_out} exists and is not a bag of an earlier replay: move it")
        shutil.rmtree(bag_out)
    return bag_out
