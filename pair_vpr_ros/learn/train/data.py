"""Place-aware batches for both training stages.

A batch holds P places x k images of each place (stage one: k = 2, a pair; stage two: k = 4).
`PlaceBatchSampler` shuffles places once per epoch with the same seed on every rank, cuts the
order into global batches of P x world_size places and hands each rank its own P: no place
appears twice in a global batch, and every rank runs the same number of equal-sized batches.
Its indices carry the epoch, ``(epoch, place)``, so the loader's workers can stay alive between
epochs and still draw each epoch's own views.

Views have a capture condition when the places' views cycle through ``conditions`` of them (the
demo place datasets: view ``k.png`` is lit by lighting ``k mod 3``); -1 = unknown. With
``pair_conditions`` a place's k views are k/2 pairs that share a condition, so each anchor has a
positive in its own condition and positives in others (stage two mines both in equal shares).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.image_files import read_rgb
from pair_vpr_ros.learn.places import PlaceCollection
from pair_vpr_ros.learn.train.common import DistContext
from pair_vpr_ros.learn.train.config import TrainConfig
from pair_vpr_ros.model import preprocess


@dataclass(frozen=True)
class AugmentConfig:
    """Light photometric/geometric jitter; ``None`` in the datasets means no augmentation.

    ``grey`` and ``exposure`` make a model that also works on mono8 cameras and under other
    exposure: a grey image is what `images.convert` makes of a mono8 frame (the grey value in all
    three channels)."""

    crop_scale: tuple[float, float] = (0.7, 1.0)  # area fraction of a random crop (aspect kept)
    brightness: float = 0.2  # +- fraction of the pixel range
    contrast: float = 0.2  # +- fraction around the image mean
    grey: float = 0.0  # probability of turning the image grey (ITU-R BT.601 luma)
    exposure: float = 0.0  # gain drawn log-uniformly from [1/(1+e), 1+e]


def grey_rgb(rgb: np.ndarray) -> np.ndarray:
    """[H,W,3] -> [H,W,3] float32: BT.601 luma (what a mono camera sees) in all channels."""
    luma = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return np.repeat(luma[..., None], 3, axis=2)


def augment_rgb(rgb: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """[H,W,3] uint8 -> [h,w,3] uint8: random crop, grey, exposure, brightness and contrast."""
    h, w = rgb.shape[:2]
    side = float(np.sqrt(rng.uniform(*aug.crop_scale)))
    ch, cw = max(1, round(h * side)), max(1, round(w * side))
    y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    out = rgb[y : y + ch, x : x + cw].astype(np.float32)
    if aug.grey > 0 and rng.uniform() < aug.grey:
        out = grey_rgb(out)
    if aug.exposure > 0:
        out = out * float(np.exp(rng.uniform(-1.0, 1.0) * np.log1p(aug.exposure)))
    contrast = 1.0 + rng.uniform(-aug.contrast, aug.contrast)
    shift = 255.0 * rng.uniform(-aug.brightness, aug.brightness)
    out = (out - out.mean()) * contrast + out.mean() + shift
    return np.clip(out, 0, 255).astype(np.uint8)


GREY_ONLY = AugmentConfig(crop_scale=(1.0, 1.0), brightness=0.0, contrast=0.0)


def image_tensor(
    path: object, size: int, rng: np.random.Generator | None, aug: AugmentConfig | None
) -> torch.Tensor:
    """Image file -> normalised [3,size,size] (``pair_vpr_ros.model.preprocess``)."""
    rgb = read_rgb(path)
    if aug is not None and rng is not None:
        rgb = augment_rgb(rgb, rng, aug)
    return preprocess(np.ascontiguousarray(rgb), size=size)


def near_identical(images: Tensor, shift: int = 2, grey_levels: float = 2.0) -> Tensor:
    """[T,3,S,S] normalised images -> copies moved by up to ``shift`` pixels (edges repeated)
    with Gaussian noise of ``grey_levels`` / 255 (in normalised units): what a camera sees of
    a place it has not moved from."""
    t, _, h, w = images.shape
    padded = F.pad(images, (shift, shift, shift, shift), mode="replicate")
    offsets = torch.randint(0, 2 * shift + 1, (t, 2)).tolist()
    moved = torch.stack(
        [padded[i, :, dy : dy + h, dx : dx + w] for i, (dy, dx) in enumerate(offsets)]
    )
    return moved + torch.randn_like(moved) * (grey_levels / 255.0 / 0.226)


def view_condition(path: object, conditions: int) -> int:
    """Condition of a view named ``<k>.<ext>``: k mod ``conditions``; -1 if unknown."""
    stem = getattr(path, "stem", str(path).rsplit("/", 1)[-1].split(".")[0])
    return int(stem) % conditions if conditions > 0 and stem.isdigit() else -1


def choose_views(
    conds: list[int], k: int, rng: np.random.Generator, pair_conditions: bool
) -> np.ndarray:
    """k view indices of one place: random, or (``pair_conditions``, k even) k/2 pairs of views
    that share a condition, from k/2 different conditions when the place has them."""
    if pair_conditions and k % 2 == 0:
        by_cond: dict[int, list[int]] = {}
        for i, c in enumerate(conds):
            if c >= 0:
                by_cond.setdefault(c, []).append(i)
        usable = sorted(c for c, views in by_cond.items() if len(views) >= 2)
        if len(usable) >= k // 2:
            picked = rng.choice(usable, size=k // 2, replace=False)
            return np.concatenate([rng.choice(by_cond[c], 2, replace=False) for c in picked])
    return rng.choice(len(conds), size=k, replace=False)


class PlaceImagesDataset(Dataset):
    """Item = one place: (images [k,3,S,S], labels [k] int64, conditions [k] int64). Places with
    < k images dropped. The index is a place or (epoch, place) (see the module docstring)."""

    def __init__(
        self,
        places: PlaceCollection,
        images_per_place: int,
        size: int,
        augment: AugmentConfig | None = None,
        seed: int = 0,
        conditions: int = 0,
        pair_conditions: bool = False,
        grey_places: float = 0.0,
    ) -> None:
        keep = [i for i, p in enumerate(places.places) if len(p) >= images_per_place]
        if not keep:
            raise DatasetError(
                f"no place of {places.name} has >= {images_per_place} images "
                f"({len(places)} places checked)"
            )
        self.places = [places.places[i] for i in keep]
        self.labels = keep  # labels stay those of the collection
        self.dropped_places = len(places) - len(keep)
        self.k, self.size, self.augment, self.seed = images_per_place, size, augment, seed
        self.conds = [[view_condition(v, conditions) for v in p] for p in self.places]
        self.pair_conditions = pair_conditions
        self.grey_places = grey_places
        # a grey place: every view grey, with the jitter of the other views (or none)
        self.grey_augment = replace(augment or GREY_ONLY, grey=1.0)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.places)

    def __getitem__(self, index: int | tuple[int, int]) -> tuple[torch.Tensor, ...]:
        epoch, index = index if isinstance(index, tuple) else (self.epoch, index)
        # Seeded by (seed, epoch, place): identical across worker counts and on resume.
        rng = np.random.default_rng([self.seed, epoch, index])
        paths, conds = self.places[index], self.conds[index]
        chosen = choose_views(conds, self.k, rng, self.pair_conditions)
        # drawn only when on, so that runs without grey places keep their random streams
        grey = self.grey_places > 0 and rng.uniform() < self.grey_places
        augment = self.grey_augment if grey else self.augment
        images = torch.stack([image_tensor(paths[i], self.size, rng, augment) for i in chosen])
        labels = torch.full((self.k,), self.labels[index], dtype=torch.int64)
        return images, labels, torch.tensor([conds[i] for i in chosen], dtype=torch.int64)


class PlaceBatchSampler(Sampler[list[int]]):
    """Yields this rank's lists of P place indices; see the module docstring."""

    def __init__(
        self,
        num_places: int,
        places_per_batch: int,
        rank: int = 0,
        world_size: int = 1,
        seed: int = 0,
        shuffle: bool = True,
    ) -> None:
        self.n, self.p, self.rank, self.world = num_places, places_per_batch, rank, world_size
        self.seed, self.shuffle, self.epoch, self.start_batch = seed, shuffle, 0, 0
        if len(self) == 0:
            raise DatasetError(
                f"{num_places} places cannot fill one batch of {places_per_batch} places on each "
                f"of {world_size} processes: lower --places-per-batch or add data"
            )

    def set_epoch(self, epoch: int, start_batch: int = 0) -> None:
        """Select the epoch's order; ``start_batch`` skips batches already done (resume)."""
        self.epoch, self.start_batch = epoch, start_batch

    def __len__(self) -> int:
        return self.n // (self.p * self.world)

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        if self.shuffle:
            order = torch.randperm(
                self.n, generator=torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            ).tolist()
        else:
            order = list(range(self.n))
        span = self.p * self.world
        for b in range(self.start_batch, len(self)):
            start = b * span + self.rank * self.p
            yield [(self.epoch, i) for i in order[start : start + self.p]]


def collate_places(batch: list[tuple[torch.Tensor, ...]]) -> tuple[torch.Tensor, ...]:
    """P items of ([k,3,S,S], [k], [k]) -> (images [P,k,3,S,S], labels [P,k], conditions
    [P,k])."""
    return tuple(torch.stack(parts) for parts in zip(*batch, strict=True))


@dataclass
class PlaceData:
    """One stage's training data on this process: places, this rank's batches, their loader."""

    dataset: PlaceImagesDataset
    sampler: PlaceBatchSampler
    loader: DataLoader


def place_data(
    places: PlaceCollection,
    images_per_place: int,
    size: int,
    cfg: TrainConfig,
    ctx: DistContext,
    pair_conditions: bool = False,
) -> PlaceData:
    """Batches of ``cfg.places_per_batch`` places x ``images_per_place`` images of ``size``."""
    if cfg.augment:
        augment = AugmentConfig(grey=cfg.grey, exposure=cfg.exposure)
    else:  # grey views alone are no jitter: mono8 cameras need them either way
        augment = replace(GREY_ONLY, grey=cfg.grey) if cfg.grey > 0 else None
    dataset = PlaceImagesDataset(
        places,
        images_per_place,
        size,
        augment,
        seed=cfg.seed,
        conditions=cfg.conditions,
        pair_conditions=pair_conditions,
        grey_places=cfg.grey_places,
    )
    sampler = PlaceBatchSampler(
        len(dataset), cfg.places_per_batch, ctx.rank, ctx.world_size, cfg.seed
    )
    loader = make_loader(dataset, sampler, cfg.workers, ctx.device.type == "cuda")
    return PlaceData(dataset, sampler, loader)


def make_loader(
    dataset: PlaceImagesDataset, sampler: PlaceBatchSampler, workers: int, pin: bool
) -> DataLoader:
    return DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=workers,
        collate_fn=collate_places,
        pin_memory=pin,
        persistent_workers=workers > 0,  # the epoch travels in the indices
    )
