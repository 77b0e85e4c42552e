"""`compact_map`: a saved map rewritten into a new folder with the growth policy applied from its
stored signatures and links, and its dense tokens in another codec (`pairvpr-map compact IN --out
OUT`).

Keyframes are visited in id order, as the pipeline met them. A keyframe whose links to earlier
keyframes (its loops with a confident pose) lead to a kept keyframe of its appearance
(`find_representative`, the pipeline's rule on pose and appearance) that its own re-ranking
recognised (the live rule's third condition: the re-rank score its link keeps is at or above
`score_threshold`; a keyframe one hop away whose score the keyframe's links do not keep may not
represent it, so compact never drops a keyframe the live rule would have stored) is dropped and
recorded as represented. Links written before scores were kept (issue 48) are judged on pose and
appearance alone, as before, and the result says how many keyframes were. The others are
copied (descriptor, dense tokens re-encoded, metadata, features, signature) with new ids 0, 1, 2,
...; a keyframe linked to one stored without features (its lender) is never dropped. The links
between kept keyframes and the represented rows (their representatives renumbered, or followed to a
kept one) are copied too. A map without signatures (saved before them) is only re-encoded, and the
result says so. The new map is written beside OUT and renamed to OUT when complete (merge.py's
`publish_map`): a crash leaves no OUT.
"""

from __future__ import annotations

import functools
import os
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError
from pair_vpr_ros.place_map.dense_codec import DEFAULT_CODEC, check_codec
from pair_vpr_ros.place_map.growth.policy import GrowthConfig, find_representative, is_recent
from pair_vpr_ros.place_map.growth.tables import GrowthTables, Represented
from pair_vpr_ros.place_map.manifest import read_manifest
from pair_vpr_ros.place_map.merge import compacting, publish_map, remove_stale, work_folder
from pair_vpr_ros.place_map.place_map import PlaceMap

CHUNK = 64  # keyframes whose dense tokens are read at once


@dataclass
class CompactResult:
    """What `compact_map` wrote: keyframes in and kept, represented (before and after), the
    dense codec, bytes on disk of IN and OUT, and notes (e.g. no signatures: policy skipped)."""

    out: str
    keyframes_in: int = 0
    stored: int = 0
    represented_before: int = 0
    represented: int = 0
    codec: str = DEFAULT_CODEC
    bytes_in: int = 0
    bytes_out: int = 0
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # e.g. IN misses saved keyframes

    def line(self) -> str:
        return (
            f"compacted {self.keyframes_in} keyframes into {self.out}: {self.stored} stored, "
            f"{self.represented} represented ({self.represented - self.represented_before} "
            f"new), dense tokens {self.codec}; {self.bytes_in:,} -> {self.bytes_out:,} bytes"
        )


def compact_map(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    codec: str = DEFAULT_CODEC,
    policy: bool = True,
    growth: GrowthConfig | None = None,
    fingerprint: str | None = None,
    score_threshold: float = 0.0,
) -> CompactResult:
    """Compact the saved map `src` into the new folder `out` (module docstring) -> result.
    codec: "p4", "q4", "q4a" or "f16" (p4 of a p4 map keeps its basis); policy False: re-encode
    only; fingerprint: refuse a map of another model; score_threshold: the detector's (the
    re-rank score a representative must have had, the live rule's). ConfigError (`out`
    exists, bad codec), OutputError (`out`'s folder not writable), MapError (`src` not a map,
    damaged, of an old format; a full disk), MapFingerprintError; `out` is not created then. A
    map whose store misses saved keyframes (its -wal lost) is compacted from what it holds,
    with a warning (the way to go on with it)."""
    check_codec(codec)
    source, target = Path(src).expanduser().resolve(), Path(out).expanduser().resolve()
    _check_paths(source, target)
    remove_stale(target)
    work = work_folder(target)  # named as merge's, so that remove_stale clears it after a kill
    try:
        with _open(source, fingerprint) as m:
            result = CompactResult(out=str(target), keyframes_in=len(m), codec=codec)
            result.warnings += [m.load_note] if m.load_note else []
            result.bytes_in = _bytes(source)
            tables = m.growth
            counts = tables.counts()
            result.represented_before = counts.represented
            if policy and counts.signatures == 0:
                result.notes.append(
                    f"{source} has no appearance signatures (saved before map_growth): its "
                    "keyframes are only re-encoded"
                )
            rule = Rule(growth or GrowthConfig(), score_threshold)
            dropped = _dropped(m, tables, rule) if policy else {}
            if rule.unscored:
                result.notes.append(
                    f"{rule.unscored} keyframes of {source} have links without a re-rank score "
                    "(saved before issue 48): they were judged on pose and appearance alone"
                )
            with compacting(target, work):
                new = _copy(m, tables, dropped, codec, work)
                result.stored, result.represented = len(new), new.growth.counts().represented
                publish_map(new, target)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.bytes_out = _bytes(target)
    return result


def _check_paths(source: Path, target: Path) -> None:
    if target.exists():
        raise ConfigError(
            f"--out {target} exists: compact never writes into an existing folder; give a new one"
        )
    if not target.parent.is_dir():
        raise ConfigError(f"--out {target}: its parent folder does not exist; create it first")
    if not source.is_dir():
        raise ConfigError(f"input map {source} does not exist or is not a folder")
    if source in target.parents:
        raise ConfigError(f"--out {target} lies inside the input map: give a folder elsewhere")


def _open(source: Path, fingerprint: str | None) -> PlaceMap:
    try:
        version = read_manifest(source).format_version
    except MapError as err:
        raise MapError(f"input map {source} cannot be compacted: {err}") from err
    if version < 3:
        raise MapError(
            f"input map {source} is of format version {version}: compact reads formats 3-4; load "
            "it in the node or a replay (--map-dir) and save it once to convert it, then compact"
        )
    try:  # keyframes its -wal lost: compacted from what it holds, with a warning
        m = PlaceMap.load(source, read_only=True, missing_ok=True)
    except MapError as err:
        raise type(err)(f"input map {source} cannot be compacted: {err}") from err
    if fingerprint is not None and m.fingerprint != fingerprint:
        m.close()
        raise MapFingerprintError(
            f"input map {source} holds model {m.fingerprint!r}, not {fingerprint!r}: compact "
            "maps of that model only, or leave out --fingerprint"
        )
    return m


@dataclass
class Rule:
    """The growth rule compact applies: the policy's limits and the detector's threshold;
    `unscored` counts the keyframes judged without scores (links saved before them)."""

    config: GrowthConfig
    score_threshold: float
    unscored: int = 0

    def recognised(self, scored: list[tuple[int, tuple, float | None]]) -> set[int] | None:
        """The earlier keyframes a keyframe's re-ranking recognised, from its links' scores
        (None: its links keep no score, saved before them)."""
        if all(score is None for *_, score in scored):
            self.unscored += 1
            return None
        return {k for k, _, score in scored if score is not None and score >= self.score_threshold}


def _dropped(m: PlaceMap, tables: GrowthTables, rule: Rule) -> dict[int, tuple]:
    """{id: (representative id, distance)} of the keyframes the policy drops, in id order."""
    dropped: dict[int, tuple] = {}
    config = rule.config
    metas = m.all_meta()

    def stamp_and_identity(kf_id: int) -> tuple[float, str, str]:
        return (metas[kf_id].stamp, *m.identity(metas[kf_id]))

    def kept_signature(query: tuple, known: set[int] | None, kf_id: int):
        if kf_id in dropped or is_recent(query, stamp_and_identity(kf_id), config):
            return None
        if known is not None and kf_id not in known:  # not recognised: the live rule's 3rd
            return None
        return tables.signature(kf_id)

    # a keyframe that lends its features to one stored without them is kept (its geometry)
    lenders = {k for q in range(len(m)) if not m.features(q) for k, _ in tables.links(q)}
    for q in range(len(m)):
        if q in lenders:
            continue
        query = stamp_and_identity(q)

        signature = tables.signature(q)
        scored = [link for link in tables.scored_links(q) if link[0] < q]  # its loops, T_K_Q
        if signature is None or not scored:
            continue
        posed, known = [(k, t_k_q) for k, t_k_q, _ in scored], rule.recognised(scored)
        found = find_representative(signature, posed, tables.links,
                                    functools.partial(kept_signature, query, known),
                                    config)  # fmt: skip
        if found is not None:
            dropped[q] = found
    return dropped


def _copy(m: PlaceMap, tables: GrowthTables, dropped: dict, codec: str, work: Path) -> PlaceMap:
    config = replace(m.index_config, dense_codec=codec)
    new = PlaceMap(m.desc_dim, m.dense_shape, m.fingerprint, config, work_dir=work)
    new.adopt_dense_basis(m.dense_basis)  # p4: keep the input's basis (fitted with the model)
    try:
        new_id: dict[int, int] = {}
        metas = m.all_meta()
        for start in range(0, len(m), CHUNK):
            ids = [i for i in range(start, min(start + CHUNK, len(m))) if i not in dropped]
            dense, desc = m.get_dense(ids), m.get_desc(ids)
            for row, kf_id in enumerate(ids):
                meta = replace(metas[kf_id], id=-1)
                new_id[kf_id] = new.add(desc[row], dense[row], meta, m.features(kf_id))
                signature = tables.signature(kf_id)
                if signature is not None:
                    new.growth.add_signature(new_id[kf_id], signature)
        _copy_growth(m, tables, dropped, new_id, new)
    except BaseException:
        new.close()
        raise
    return new


def _copy_growth(m: PlaceMap, tables: GrowthTables, dropped: dict, new_id: dict, new) -> None:
    """Links between kept keyframes, old represented rows and the newly dropped ones."""

    def kept(kf_id: int) -> int:  # a dropped representative: follow it to a kept one
        while kf_id in dropped:
            kf_id = dropped[kf_id][0]
        return new_id[kf_id]

    for a in new_id:
        for b, t_b_a, score in tables.scored_links(a):
            if b < a and b in new_id:
                new.growth.add_link(new_id[a], new_id[b], t_b_a, score)
    for row in tables.represented():
        new.growth.add_represented(replace(row, representative=kept(row.representative)))
    for kf_id, (rep, distance) in dropped.items():
        meta = m.meta(kf_id)
        robot, session = m.identity(meta)
        new.growth.add_represented(Represented(meta.stamp, robot, session, kept(rep), distance))


def _bytes(directory: Path) -> int:
    return sum(
        p.stat().st_size for p in directory.iterdir() if p.is_file() and p.name != "map.lock"
    )
