"""milvus_consistency "Bounded" (place_map/milvus/fresh.py): the map's newest rows, searched in
the node, under the same rules as the server's filter, merged with the server's answer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_place_map_persist import DIM, SHAPE, desc_for

from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.milvus.expr import Exclusion
from pair_vpr_ros.place_map.milvus.fresh import FreshRows, local_mask, merge

N = 40


def test_the_node_side_filter_equals_the_server_filter(milvus):
    """milvus_consistency Bounded searches the newest rows in the node: under the same rules it
    must let through exactly the rows the server's filter lets through."""
    rng = np.random.default_rng(8)
    names = rng.choice(["a", "b"], N), rng.choice(["s1", "s2"], N), rng.integers(0, 30, N)
    rows = [(str(r), str(s), float(t)) for r, s, t in zip(*names, strict=True)]
    strong = replace(milvus, milvus_consistency="Strong")
    with PlaceMap(DIM, SHAPE, "fp", index=strong) as m:
        index = m._index
        for i, row in enumerate(rows):
            index.add(desc_for(i)[None], [row])
        sizes = []
        for stamp, window, limit in ((10.0, 5.0, N - 3), (20.0, 0.0, N), (3.0, 40.0, 10)):
            rule = Exclusion(stamp, window, limit, "a", "s1")
            server = set(index.search(desc_for(0), N, exclusion=rule)[0].tolist())
            local = np.flatnonzero(local_mask(index._rows, 0, N, None, rule))
            assert set(local.tolist()) == server
            sizes.append(len(server))
        assert 0 < min(sizes) < N  # the rules leave some rows out, not all
        allowed = rng.random(N) < 0.5
        server = set(index.search(desc_for(0), N, max_id=29, allowed=allowed)[0].tolist())
        assert set(np.flatnonzero(local_mask(index._rows, 0, 30, allowed, None))) == server


def test_merge_keeps_the_best_of_each_id_once():
    a = (np.array([5, 2, 9]), np.array([0.9, 0.5, 0.1], np.float32))
    b = (np.array([7, 5]), np.array([0.7, 0.9], np.float32))
    ids, sims = merge(a, b, 3)
    assert ids.tolist() == [5, 7, 2] and np.allclose(sims, [0.9, 0.7, 0.5])


def test_fresh_rows_age_out():
    fresh = FreshRows(window_s=0.0)
    fresh.written(3)
    assert FreshRows().first(10) == 10  # nothing written: all visible
    assert fresh.first(10) == 10  # a zero window: aged out at once
    kept = FreshRows()
    kept.written(3)
    kept.written(6)
    assert kept.first(10) == 3 and kept.first(2) == 2
