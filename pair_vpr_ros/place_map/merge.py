"""Merging saved place maps into a new one (`pairvpr-map merge A B ... --out C`).

Every input is opened read-only (never changed) and must come from the same model: fingerprint,
descriptor size and dense-token shape. Keyframes are copied in input order with new ids
0, 1, 2, ... (A's first, then B's: no collisions), with their descriptors, dense tokens, metadata
(robot, session, stamp, pose) and stored features. The result is saved into a temporary folder
beside `--out` and renamed to `--out` only when complete, so a crash or a failure leaves no
`--out` at all (and an existing `--out` is refused before any work).

Two inputs with keyframes of the same robot and session are merged with a warning, not refused:
the pair (robot, session) then names the keyframes of both, which is right when one map
continues the other's session (saved twice) and harmless otherwise for the search itself
(recent-keyframe exclusion inside that session works by stamp, so copies of one keyframe never
match each other); but the pose graph would take them for one trajectory, so the warning says
which inputs share which session.

Index kind "milvus" (docs/milvus.md): the merged map gets its own writer key in the first
input's collection (or the one `milvus_uri` / `milvus_collection` name), so the inputs' rows
are never touched; inputs of any kinds mix, since keyframes are copied from each map's own
descriptors. A merge that fails deletes the rows it wrote (closing a never-saved map does; after
the save into the temporary folder, `drop_index_rows`).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from pair_vpr_ros.errors import (
    ConfigError,
    MapError,
    MapFingerprintError,
    OutputError,
    disk_full,
    os_reason,
)
from pair_vpr_ros.identity import DEFAULT_ROBOT, LEGACY_SESSION
from pair_vpr_ros.place_map.index import IndexConfig
from pair_vpr_ros.place_map.place_map import PlaceMap

CHUNK = 64  # keyframes whose dense tokens are read at once
MILVUS_FIELDS = ("milvus_uri", "milvus_collection", "milvus_index", "milvus_token_env")


@dataclass
class MergeResult:
    out: str
    keyframes: int = 0
    inputs: list[dict] = field(default_factory=list)  # dir, keyframes, first_id (new ids)
    warnings: list[str] = field(default_factory=list)

    def line(self) -> str:
        parts = ", ".join(f"{i['dir']} ({i['keyframes']})" for i in self.inputs)
        return f"merged {self.keyframes} keyframes of {parts} into {self.out}"


def merge_maps(
    inputs: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    index: str | IndexConfig | None = None,
    progress: bool = False,
    milvus_uri: str | None = None,
    milvus_collection: str | None = None,
) -> MergeResult:
    """Merge the saved maps `inputs` (at least two) into the new folder `out` -> MergeResult.
    index: the merged map's index: an IndexConfig, or a kind that keeps the first input's
    other settings (default: the first input's settings); milvus_uri / milvus_collection
    replace the first input's (needed for kind "milvus" when the first input is not one).
    ConfigError (too few inputs, one given twice, `out` exists, index settings), MapError /
    MapFingerprintError (an input is not a map, is damaged, or comes from another model),
    OutputError (`out`'s folder cannot be written, a full disk there); `out` is not created
    then."""
    target = Path(out).expanduser().resolve()
    dirs = [Path(d).expanduser().resolve() for d in inputs]
    _check_arguments(dirs, target)
    remove_stale(target)
    work = work_folder(target)
    maps: list[PlaceMap] = []
    try:
        for d in dirs:
            maps.append(_open(d))
        _check_same_model(maps)
        config = merged_index(maps[0], index, milvus_uri, milvus_collection)
        result = MergeResult(out=str(target))
        result.warnings += [m.load_note for m in maps if m.load_note]
        result.warnings += _shared_sessions(maps)
        with compacting(target, work, "merging"):
            merged = _copy(maps, config, result, work, progress)
            publish_map(merged, target)
    finally:
        for m in maps:
            m.close()
        shutil.rmtree(work, ignore_errors=True)
    return result


def work_folder(target: Path) -> Path:
    """The folder a merge or compact works in beside `target` (`.OUT.merging-PID.work`), made
    before any work: OutputError when `target`'s folder cannot be written."""
    work = target.parent / f".{target.name}.merging-{os.getpid()}.work"
    try:
        work.mkdir(exist_ok=True)
    except OSError as err:
        raise OutputError(
            f"cannot write --out {target}: {target.parent} is not writable ({os_reason(err)}); "
            "pick a writable folder"
        ) from err
    return work


@contextmanager
def compacting(target: Path, work: Path, what: str = "compacting") -> Iterator[None]:
    """A full disk (or another OSError) while the new map is written in `work` -> one
    OutputError with this tool's advice (the map's own, meant for a live map, does not apply:
    nothing was written to --out, the inputs are unchanged)."""
    try:
        yield
    except (MapError, OSError) as err:
        chain = [err, err.__cause__, getattr(err.__cause__, "__cause__", None)]
        full = next((e for e in reversed(chain) if e is not None and disk_full(e)), None)
        if full is None and not isinstance(err, OSError):
            raise  # an input's own error (damaged, another model): its message says it
        raise OutputError(
            f"{what} into --out {target} failed: {os_reason(full or err)}, writing in {work}; "
            f"nothing was written to --out and the inputs are unchanged: free disk space in "
            f"{target.parent} (or pick another --out) and run it again"
        ) from err


def remove_stale(target: Path) -> None:
    """The folders beside `target` that a merge into it left when it was killed part-way
    (SIGKILL, power loss: no clean-up ran); a merge whose process still runs keeps its own."""
    for path in target.parent.glob(f".{target.name}.merging-*"):
        pid = path.name.rsplit("-", 1)[1].split(".")[0]
        if pid.isdigit() and not _running(int(pid)):
            shutil.rmtree(path, ignore_errors=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def _check_arguments(dirs: list[Path], target: Path) -> None:
    if len(dirs) < 2:
        raise ConfigError(f"merge needs at least two maps, got {len(dirs)}: give A B ... --out C")
    if len(set(dirs)) < len(dirs):
        raise ConfigError("a map is given twice: give each input map once")
    if target.exists():
        raise ConfigError(
            f"--out {target} exists: a merge never writes into an existing folder; give a new one"
        )
    if not target.parent.is_dir():
        raise ConfigError(f"--out {target}: its parent folder does not exist; create it first")
    if target in dirs or any(d in target.parents for d in dirs):
        raise ConfigError(f"--out {target} lies inside an input map: give a folder elsewhere")


def _open(d: Path) -> PlaceMap:
    if not d.is_dir():
        raise ConfigError(f"input map {d} does not exist or is not a folder")
    try:
        return PlaceMap.load(d, read_only=True, legacy_identity=(DEFAULT_ROBOT, LEGACY_SESSION))
    except MapError as err:
        raise type(err)(f"input map {d} cannot be merged: {err}") from err


def merged_index(
    first: PlaceMap, index, milvus_uri: str | None, milvus_collection: str | None
) -> IndexConfig:
    """The merged map's IndexConfig (see merge_maps); ConfigError when milvus settings are
    missing or given for another kind."""
    if isinstance(index, IndexConfig):
        return index
    base = first.index_config
    kind = index or base.kind
    fields = {k: v for k, v in (("milvus_uri", milvus_uri), ("milvus_collection",
              milvus_collection)) if v is not None}  # fmt: skip
    if kind != "milvus" and fields:
        raise ConfigError(
            f"--milvus-uri and --milvus-collection apply to a milvus index only, the merged "
            f"map's index is {kind!r}: add --index milvus or leave them out"
        )
    if kind == "milvus" and base.kind != "milvus" and "milvus_uri" not in fields:
        raise ConfigError(
            f"--index milvus needs --milvus-uri (a milvus-lite .db file or http://host:19530): "
            f"the first map, {first.directory}, has a {base.kind!r} index and no Milvus settings"
        )
    if kind != "milvus":  # a FAISS map records no Milvus settings
        plain = IndexConfig()
        fields = {k: getattr(plain, k) for k in MILVUS_FIELDS}
    return replace(base, kind=kind, **fields)


def _check_same_model(maps: list[PlaceMap]) -> None:
    first = maps[0]
    for m in maps[1:]:
        if (m.fingerprint, m.desc_dim, m.dense_shape) != (
            first.fingerprint, first.desc_dim, first.dense_shape,
        ):  # fmt: skip
            raise MapFingerprintError(
                f"maps of different models cannot be merged: {first.directory} holds model "
                f"{first.fingerprint!r} (descriptors {first.desc_dim}, dense tokens "
                f"{list(first.dense_shape)}), {m.directory} holds {m.fingerprint!r} (descriptors "
                f"{m.desc_dim}, dense tokens {list(m.dense_shape)}): merge only maps built with "
                "the same weights and image size"
            )


def _shared_sessions(maps: list[PlaceMap]) -> list[str]:
    seen: dict[tuple[str, str], list[str]] = {}
    for m in maps:
        for key in {(k.robot, k.session) for k in m.all_meta()}:
            seen.setdefault(key, []).append(str(m.directory))
    return [
        f"robot {robot!r} session {session!r} has keyframes in {' and '.join(where)}: merged "
        "under one name (kept; a pose graph would take them for one trajectory)"
        for (robot, session), where in sorted(seen.items())
        if len(where) > 1
    ]


def _copy(
    maps: list[PlaceMap], index: IndexConfig, result: MergeResult, work: Path, progress: bool
) -> PlaceMap:
    first = maps[0]
    merged = PlaceMap(first.desc_dim, first.dense_shape, first.fingerprint, index, work_dir=work)
    merged.adopt_dense_basis(next((m.dense_basis for m in maps if m.dense_basis), None))
    total = sum(len(m) for m in maps)
    try:
        with tqdm(total=total, unit="keyframe", desc="merge", disable=not progress) as bar:
            for m in maps:
                result.inputs.append(
                    {"dir": str(m.directory), "keyframes": len(m), "first_id": len(merged)}
                )
                metas, offset = m.all_meta(), len(merged)
                for start in range(0, len(m), CHUNK):
                    ids = list(range(start, min(start + CHUNK, len(m))))
                    dense, desc = m.get_dense(ids), m.get_desc(ids)
                    for row, kf_id in enumerate(ids):
                        meta = replace(metas[kf_id], id=-1)
                        merged.add(desc[row], dense[row], meta, m.features(kf_id))
                    bar.update(len(ids))
                _copy_growth(m, merged, offset)
        result.keyframes = len(merged)
    except BaseException:
        merged.close()  # milvus: deletes its rows, which no saved record names
        raise
    return merged


def _copy_growth(m: PlaceMap, merged: PlaceMap, offset: int) -> None:
    """An input map's signatures and links, ids shifted by `offset`: a keyframe stored without
    features (map_growth) finds its lender's through its links (loops/growth.py)."""
    tables = m.growth
    if not tables.present():
        return
    for kf_id in range(len(m)):
        signature = tables.signature(kf_id)
        if signature is not None:
            merged.growth.add_signature(kf_id + offset, signature)
        for other, t_other_kf, score in tables.scored_links(kf_id):
            if other < kf_id:
                merged.growth.add_link(kf_id + offset, other + offset, t_other_kf, score)


def publish_map(merged: PlaceMap, target: Path) -> None:
    """Save `merged` into a temporary folder beside `target`, then rename it to `target`."""
    tmp = target.parent / f".{target.name}.merging-{os.getpid()}"
    closed = False
    try:
        merged.save(tmp)
        if target.exists():
            raise ConfigError(f"--out {target} appeared while merging: the merge is not saved")
        merged.close()  # releases the folder's lock before the rename
        closed = True
        os.rename(tmp, target)
    except BaseException:
        if not closed:  # no saved map will name its rows (a failed rename leaves them: prune)
            merged.drop_index_rows()
        merged.close()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
