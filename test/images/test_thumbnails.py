"""Keyframe images kept for loop images: shrunk, JPEG in memory within a byte budget (oldest
first out, a stamp check so a cleared map's ids never show another image), or files."""

from __future__ import annotations

import numpy as np
from bag_fixtures import textured

from pair_vpr_ros.images.thumbnails import FolderThumbnails, MemoryThumbnails, shrink


def test_shrink_scales_the_longer_side_and_never_enlarges():
    big = np.zeros((480, 640, 3), np.uint8)
    small = shrink(big, 320)
    assert small.rgb.shape == (240, 320, 3) and small.scale == 0.5
    same = shrink(big[:100, :100], 320)
    assert same.rgb.shape == (100, 100, 3) and same.scale == 1.0


def test_memory_store_keeps_within_its_budget_oldest_out():
    images = [textured(seed) for seed in range(6)]
    store = MemoryThumbnails(max_bytes=1)  # smaller than one image: nothing stays
    store.put(0, 0.0, images[0])
    assert len(store) == 0 and store.get(0, 0.0) is None
    store = MemoryThumbnails(max_bytes=10**6)
    for i, rgb in enumerate(images):
        store.put(i, float(i), rgb)
    one = store.nbytes // 6
    store.max_bytes = 3 * one + one // 2
    store.put(6, 6.0, images[0])  # over the budget: the oldest go until it fits
    assert [store.get(i, float(i)) is None for i in range(7)] == [True] * 4 + [False] * 3
    kept = store.get(5, 5.0)
    assert kept.scale == 1.0 and np.abs(kept.rgb.astype(int) - images[5]).mean() < 8  # JPEG
    assert store.get(5, 99.0) is None  # another keyframe with the same id (a cleared map)
    assert MemoryThumbnails(max_bytes=0).get(0, 0.0) is None


def test_folder_store_writes_one_file_a_key(tmp_path):
    store = FolderThumbnails(tmp_path, max_side=80)
    thumb = store.put(1234, textured(1))  # 160 x 120 -> 80 x 60
    assert (tmp_path / "0001" / "1234.jpg").is_file() and FolderThumbnails.name(7) == "0000/7.jpg"
    back = store.get(1234)
    assert back.rgb.shape == thumb.rgb.shape == (60, 80, 3) and back.scale == 0.5
    assert 1234 in store and store.get(5) is None and store.nbytes > 0
