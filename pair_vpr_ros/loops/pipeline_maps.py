"""The pipeline's place map: made for the model, checked against it, saved, loaded, cleared
and a match's data read from its own map: metadata, features (or a linked keyframe's), scale
neighbours, pair scores (`PipelineMaps`, which `pipeline.LoopClosurePipeline` inherits; it works on
the pipeline's state: `model`, `index_kind`, `identity`, `maps`, `geometry`, `growth`,
`rerank_chunk`, `_place_map`, `_reset_tracking`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import MapFingerprintError, MapUnavailableError
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.odometry_scale import Neighbour
from pair_vpr_ros.identity import LEGACY_SESSION
from pair_vpr_ros.loops.frames import FrameOutcome, match_candidate
from pair_vpr_ros.loops.prior_maps import refuse_prior_target
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.loops.scoring import map_pair_scores
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap


class PipelineMaps:
    """Map life cycle of LoopClosurePipeline (pipeline.py holds the state it works on)."""

    def _new_map(self) -> PlaceMap:
        desc_dim, dense_shape = self._new_map_shapes()
        return PlaceMap(
            desc_dim=desc_dim,
            dense_shape=dense_shape,
            fingerprint=self.model.fingerprint,
            index=self.index_kind,
            dense_weight=self._dense_weight(),
        )

    def _dense_weight(self):
        """The pair decoder's first layer W [C, D] (float32 numpy), which dense codec p4 fits
        its basis for; None when the model does not expose it."""
        layer = getattr(self.model, "decoder_embed", None)
        weight = getattr(layer, "weight", None)
        return None if weight is None else weight.detach().float().cpu().numpy()

    def _check_fingerprint(self, place_map: PlaceMap) -> None:
        if place_map.fingerprint != self.model.fingerprint:
            raise MapFingerprintError(
                f"the map was built with model {place_map.fingerprint!r} but this pipeline runs "
                f"{self.model.fingerprint!r}: use the same weights and image size, or rebuild it"
            )
        want = self._new_map_shapes()
        if (place_map.desc_dim, place_map.dense_shape) != want:
            raise MapFingerprintError(
                f"the map holds descriptors of {place_map.desc_dim} and dense tokens of "
                f"{list(place_map.dense_shape)}, this model makes {want[0]} and {list(want[1])} "
                "(its manifest was edited?): rebuild the map with this model"
            )

    def _new_map_shapes(self) -> tuple[int, tuple[int, int]]:
        cfg = self.model.config
        return cfg.desc_dim, (self.model.num_patches, cfg.embed_dim)

    def save_map(
        self, directory: str | Path, overwrite: bool = False, checkpoint: bool = True
    ) -> Path:
        """checkpoint=False: the caller folds the store's WAL later (PlaceMap.checkpoint)."""
        refuse_prior_target(directory, self.maps.priors)  # a prior map is never written
        return self._place_map.save(directory, overwrite=overwrite, checkpoint=checkpoint)

    def load_map(self, directory: str | Path) -> int:
        """Replace the map by a saved one (same model required); returns its keyframe count.

        Reloading the folder the current map was saved to discards its unsaved keyframes (the
        folder is locked by the current map, so that one is closed first)."""
        refuse_prior_target(directory, self.maps.priors)  # it is searched already, read-only
        current = self._place_map
        same = current.directory is not None and current.directory == Path(directory).resolve()
        if same:
            current.close()
        loaded = None
        try:
            loaded = PlaceMap.load(
                directory, expected_fingerprint=self.model.fingerprint,
                legacy_identity=(self.identity.robot, LEGACY_SESSION),
            )  # fmt: skip
            self._check_fingerprint(loaded)
        except Exception:
            if loaded is not None:
                loaded.close()
            if same:  # the old map is gone: continue on an empty one rather than none
                self._place_map = self._new_map()
                self._reset_tracking()
            raise
        loaded.set_dense_weight(self._dense_weight())
        self._place_map = loaded
        self._reset_tracking()
        if not same:
            current.close()
        return len(loaded)

    def clear_map(self) -> None:
        self._place_map.clear()
        self._reset_tracking()

    def close(self) -> None:
        self._place_map.close()
        self.maps.close_priors()

    def _stored_features(self, match: Candidate) -> Features | None:
        return self.match_features(match)[0]

    def match_features(self, match: Candidate) -> tuple[Features | None, tuple | None]:
        """What a loop to `match` is verified and posed with: the match's features, and None;
        for one stored without (map_growth), its feature source's and (source id,
        T_match_source) (`MapGrowth.feature_source`): the pose is then composed into the
        match's frame (growth.shift_pose). The pipeline and the fleet's owner use it."""
        m = self.maps.map_of(match)
        own = m.features(match.id)
        source = None if own else self.growth.feature_source(m, match.id)
        if source is None:
            return self.geometry.unpack(own), None
        return self.geometry.unpack(m.features(source[0])), source

    def scale_neighbours(self, match: Candidate, lent: tuple | None = None) -> list[Neighbour]:
        """Keyframes recorded next to the match (`lent`: next to its feature source, whose
        features pose it), with an odometry baseline, for the scale of a monocular loop
        (`MapSearch.near`)."""
        match = match if lent is None else replace(match, id=lent[0])
        meta, near = self.maps.near(match, self.geometry.config.pose.scale_neighbours)
        # each neighbour's own features (lent ones would not fit its odometry pose)
        load = lambda i: self.geometry.unpack(self.maps.map_of(match).features(i))  # noqa: E731
        return self.geometry.neighbours(meta, near, load)

    def match_meta(
        self, outcome: FrameOutcome, loop: LoopRecord | None = None
    ) -> KeyframeMeta | None:
        """The metadata of the match of `loop` (default `outcome.loop`), from its own map."""
        best = match_candidate(outcome, loop)
        return None if best is None else self.maps.map_of(best).meta(best.id)

    def _search_groups(self, desc: np.ndarray, stamp: float) -> list[list[Candidate]] | None:
        """The candidates of a query descriptor [D]: one group of all maps together, or one a
        map with `loop_per_map`; None when there are none, or the map's Milvus did not answer
        (counted: `map_searches_skipped`; logged by the map once per outage, nothing lost)."""
        who, config = self.identity, self.config
        try:
            if config.loop_per_map:
                return self.maps.search_each(desc, stamp, who, config)
            found = self.maps.search(desc, stamp, who, config)
        except MapUnavailableError:
            self.counts.map_searches_skipped += 1
            return None
        return None if found is None else [found]

    def pair_scores(self, dense: np.ndarray, ids: list[int]) -> np.ndarray:
        """Query dense [N,D] against map keyframes `ids` -> bidirectional scores [K]."""
        return map_pair_scores(self.model, self._place_map, dense, ids, self.rerank_chunk)
