"""Dataset loaders: layouts, grouping, ground truth and their error messages."""

from __future__ import annotations

import builtins
import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_data import make_place_folders, make_utm_eval_set, place_image, write_rgb

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.eval_sets import load_eval_set, positives_within
from pair_vpr_ros.learn.image_files import ImageFiles, parse_utm_name, read_rgb
from pair_vpr_ros.learn.places import (
    concat_collections,
    gsv_image_name,
    load_gldv2,
    load_gsv_cities,
    load_place_folders,
    load_places,
    load_sfxl,
)
from pair_vpr_ros.model import preprocess

README_ROW = {
    "place_id": "130",
    "year": "2018",
    "month": "4",
    "northdeg": "15",
    "city_id": "London",
    "lat": "51.4861",
    "lon": "-0.0895151",
    "panoid": "6jFjb3wGyCkcBfq4k559ag",
}


def test_place_folders_groups_sorted_images_and_drops_small_places(tmp_path: Path) -> None:
    make_place_folders(tmp_path, places=3, per_place=2)
    write_rgb(tmp_path / "lonely" / "only.jpg", place_image(9, 0))
    (tmp_path / "place_00" / "notes.txt").write_text("not an image")
    for suffix in (".BMP", ".tif", ".tiff", ".webp", ".JPEG"):  # every images.IMAGE_SUFFIXES
        write_rgb(tmp_path / "place_01" / f"more{suffix}", place_image(1, 2))
    found = load_place_folders(tmp_path)
    assert len(found) == 3 and found.num_images == 11
    assert [p.name for p in found.places[0]] == ["img_0.png", "img_1.png"]
    assert [p.name for p in found.places[1]][:3] == ["img_0.png", "img_1.png", "more.BMP"]
    assert read_rgb(found.places[1][-1]).shape == (64, 64, 3)  # .webp decodes
    assert found.places[2][0].parent.name == "place_02"


def test_place_folder_errors_name_path_and_layout(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"missing does not exist; expected layout: ROOT/<pl"):
        load_place_folders(tmp_path / "missing")
    with pytest.raises(DatasetError, match=r"has no place subfolders"):
        load_place_folders(tmp_path)
    make_place_folders(tmp_path, places=2, per_place=1)
    with pytest.raises(DatasetError, match=r"no place with >= 2 images found under"):
        load_place_folders(tmp_path)


def test_gsv_image_name_matches_the_dataset_readme_example() -> None:
    assert gsv_image_name(README_ROW) == (
        "London_0000130_2018_04_015_51.4861_-0.0895151_6jFjb3wGyCkcBfq4k559ag.jpg"
    )


def _gsv_city(root: Path, city: str, rows: list[dict], with_images: int) -> None:
    (root / "Dataframes").mkdir(parents=True, exist_ok=True)
    with (root / "Dataframes" / f"{city}.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(README_ROW))
        writer.writeheader()
        writer.writerows(rows)
    for row in rows[:with_images]:
        write_rgb(root / "Images" / row["city_id"] / gsv_image_name(row), place_image(1, 0, 16))


def test_gsv_cities_keeps_places_with_four_images_and_counts_missing_files(tmp_path) -> None:
    rows = [dict(README_ROW, year=str(2010 + i)) for i in range(5)]  # place 130: 5 rows
    rows += [dict(README_ROW, place_id="7", year=str(2010 + i)) for i in range(3)]
    _gsv_city(tmp_path, "London", rows, with_images=7)  # one image of place 7 missing
    found = load_gsv_cities(tmp_path)
    assert len(found) == 1 and found.num_images == 5 and found.skipped_images == 1
    assert found.places[0][0].parent == tmp_path / "Images" / "London"


def test_gsv_cities_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"Dataframes does not exist; expected layout"):
        load_gsv_cities(tmp_path)
    _gsv_city(tmp_path, "London", [README_ROW], with_images=1)
    with pytest.raises(DatasetError, match=r"Paris.csv not found"):
        load_gsv_cities(tmp_path, cities=["Paris"])
    (tmp_path / "Dataframes" / "London.csv").write_text("place_id,year\n1,2\n")
    with pytest.raises(DatasetError, match=r"lacks columns \['month', 'northdeg'"):
        load_gsv_cities(tmp_path)


def test_gldv2_reads_train_csv_and_nested_image_folders(tmp_path: Path) -> None:
    ids = {"abc001": "5", "abd002": "5", "fff003": "6", "fee004": "6", "aaa005": "6"}
    lines = ["id,url,landmark_id"] + [f"{i},http://x/{i},{lm}" for i, lm in ids.items()]
    (tmp_path / "train.csv").write_text("\n".join(lines) + "\n")
    for i in list(ids)[:4]:
        write_rgb(tmp_path / "train" / i[0] / i[1] / i[2] / f"{i}.jpg", place_image(2, 0, 16))
    found = load_gldv2(tmp_path)
    assert [[p.stem for p in place] for place in found.places] == [
        ["abc001", "abd002"],
        ["fee004", "fff003"],
    ]
    assert found.skipped_images == 1
    (tmp_path / "train.csv").unlink()
    with pytest.raises(DatasetError, match=r"no .*train.csv or .*train_clean.csv"):
        load_gldv2(tmp_path)


def test_sfxl_groups_by_utm_cell_and_heading_sector(tmp_path: Path) -> None:
    def name(east: float, north: float, heading: float) -> str:
        return f"@{east}@{north}@10@S@37.7@-122.4@pano@0@{heading}@0@0@0@201901@@.jpg"

    img = place_image(3, 0, 16)
    for i, (e, n, h) in enumerate(
        [(1.0, 1.0, 10), (9.0, 5.0, 20), (1.0, 1.0, 200), (12.0, 1.0, 10), (13.0, 2.0, 15)]
    ):
        write_rgb(tmp_path / f"sub{i % 2}" / name(e, n, h), img)
    write_rgb(tmp_path / "no_coordinates.jpg", img)
    found = load_sfxl(tmp_path)
    cells = [sorted(parse_utm_name(p.name) for p in place) for place in found.places]
    assert cells == [[(1.0, 1.0), (9.0, 5.0)], [(12.0, 1.0), (13.0, 2.0)]]
    assert found.skipped_images == 1
    assert len(load_sfxl(tmp_path, heading_deg=0)) == 2  # (1,1,200) joins the first cell
    assert load_sfxl(tmp_path, heading_deg=0).places[0][0].name.startswith("@1.0@1.0@")


def test_load_places_dispatch_and_concat(tmp_path: Path) -> None:
    make_place_folders(tmp_path / "a", places=2, per_place=2)
    make_place_folders(tmp_path / "b", places=1, per_place=3)
    both = concat_collections(
        [load_places(f"folders:{tmp_path / 'a'}"), load_places(str(tmp_path / "b"))]
    )
    assert len(both) == 3 and both.num_images == 7 and both.name == "folders:a+folders:b"
    with pytest.raises(DatasetError, match=r"unknown dataset kind 'msls'"):
        load_places(f"msls:{tmp_path}")


def test_utm_eval_set_positives_within_radius(tmp_path: Path) -> None:
    make_utm_eval_set(tmp_path, places=4)
    write_rgb(tmp_path / "queries" / "@500020.00@4000000.00@near0.jpg", place_image(0, 2))
    data = load_eval_set(tmp_path)
    assert len(data.database) == 4 and len(data.queries) == 5
    assert [p.tolist() for p in data.positives] == [[0], [0], [1], [2], [3]]
    assert [p.tolist() for p in load_eval_set(tmp_path, radius_m=10.0).positives][:2] == [[0], []]


def test_numpy_fallback_equals_kdtree(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(0)
    db, q = rng.uniform(0, 100, (200, 2)), rng.uniform(0, 100, (30, 2))
    expected = positives_within(db, q, 12.0)
    real_import = builtins.__import__

    def no_scipy(name: str, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        if name.startswith("scipy"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_scipy)
    got = positives_within(db, q, 12.0)
    assert [g.tolist() for g in got] == [e.tolist() for e in expected]
    assert sum(len(e) for e in expected) > 30


def test_npy_ground_truth_and_its_errors(tmp_path: Path) -> None:
    for folder, count in (("database", 3), ("queries", 2)):
        for i in range(count):
            write_rgb(tmp_path / folder / f"{i:03d}.png", place_image(i, 0, 16))
    gt = np.array([[2, 0], [-1, -1]])  # positives per query, padded with -1
    np.save(tmp_path / "ground_truth.npy", gt)
    assert [p.tolist() for p in load_eval_set(tmp_path).positives] == [[0, 2], []]
    np.save(tmp_path / "ground_truth.npy", np.array([[True, False, True], [False] * 3]))
    assert [p.tolist() for p in load_eval_set(tmp_path).positives] == [[0, 2], []]
    gt[1] = [3, -1]
    np.save(tmp_path / "ground_truth.npy", gt)
    with pytest.raises(DatasetError, match=r"query 1 names database index outside 0..2"):
        load_eval_set(tmp_path)
    np.save(tmp_path / "ground_truth.npy", gt[:1])
    with pytest.raises(DatasetError, match=r"has 1 entries but there are 2 queries"):
        load_eval_set(tmp_path)
    (tmp_path / "ground_truth.npy").unlink()
    with pytest.raises(DatasetError, match=r"000.png has no @easting@northing@ in its name"):
        load_eval_set(tmp_path)


def test_eval_set_missing_folder_error(tmp_path: Path) -> None:
    (tmp_path / "database").mkdir()
    with pytest.raises(DatasetError, match=r"queries does not exist; expected layout: ROOT/data"):
        load_eval_set(tmp_path)


def test_image_reading_and_image_files(tmp_path: Path) -> None:
    rgb = place_image(4, 0, 20)
    path = write_rgb(tmp_path / "x.png", rgb)
    assert np.array_equal(read_rgb(path), rgb)  # PNG is lossless: RGB order preserved
    image, index = ImageFiles([path], size=28)[0]
    assert index == 0 and torch.equal(image, preprocess(rgb, size=28))
    (tmp_path / "bad.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DatasetError, match=r"^image file .*bad.jpg: OpenCV could not decode the"):
        read_rgb(tmp_path / "bad.jpg")
    with pytest.raises(DatasetError, match=r"^image file .*gone.png: cannot read it \(\[Errno"):
        read_rgb(tmp_path / "gone.png")
