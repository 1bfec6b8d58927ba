"""The training data: each source's train and validation samples, and batches that mix the sources.

A folder with ``train``/``val`` splits validates on its ``val`` split; a flat folder (real footage) holds
out whole recordings (the manifest's ``video`` column, or the image-name prefix). Every batch takes a fixed
share of every source (:class:`MixedBatchSampler`); each sample is augmented from its key alone
(:class:`AugmentedSet`), so loader workers need no per-epoch state.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset, Sampler

from companion.lab.training.augment import AugmentConfig, training_sample
from companion.lab.training.cache import ImageCache
from companion.lab.training.train_config import DataSource, TrainConfig
from companion.perception.detector.dataset import Sample, find_samples, list_splits


def held_out(group: str, fraction: float) -> bool:
    """Whether training holds out recording ``group`` for validation (a fixed share, by its name's hash)."""
    digest = hashlib.sha1(group.encode(), usedforsecurity=False).digest()
    return int.from_bytes(digest[:4], "big") / 2**32 < fraction


def source_splits(src: DataSource, cfg: TrainConfig) -> tuple[list[Sample], list[Sample]]:
    """Training and validation samples of one source (see the module docstring); raises on overlap."""
    root = Path(src.path)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {root}")
    if cfg.train_split in list_splits(root):
        train_samples = find_samples(root, cfg.train_split)
        try:
            val_samples = find_samples(root, cfg.val_split)
        except FileNotFoundError:
            val_samples = []
    else:
        every = find_samples(root, None)
        train_samples = [s for s in every if not held_out(s.group, cfg.holdout_fraction)]
        val_samples = [s for s in every if held_out(s.group, cfg.holdout_fraction)]
        held = {s.group for s in val_samples} & {s.group for s in train_samples}
        if held:
            raise ValueError(f"{src.name}: recordings in both the train and val images: {sorted(held)[:3]}")
    if cfg.max_train_images:
        train_samples = train_samples[: cfg.max_train_images]
    val_samples = val_samples[: cfg.max_val_images]
    overlap = {s.key for s in train_samples} & {s.key for s in val_samples}
    if overlap:
        raise ValueError(f"{len(overlap)} images are in both the train and val splits")
    if not train_samples:
        raise FileNotFoundError(f"{src.name}: no training images in {root}")
    return train_samples, val_samples


#: What the sampler hands the dataset: (epoch, source, image index, draw, mosaic on); ``draw`` counts how
#: often the image was drawn before in the epoch. The dataset keeps no per-epoch state, so persistent loader
#: workers (separate processes) always augment for the right epoch.
SampleKey = tuple[int, int, int, int, bool]


class AugmentedSet(Dataset[tuple[Tensor, Tensor]]):
    """Training samples: (3, S, S) uint8 image and (N, 4) boxes, augmented from the sample key."""

    def __init__(
        self,
        caches: list[ImageCache] | ImageCache,
        size_px: int,
        ref_px: int,
        seed: int,
        augment: AugmentConfig,
        *,
        donor_source: int | None = None,
        paste_onto: frozenset[int] | None = None,
    ) -> None:
        self.caches = caches if isinstance(caches, list) else [caches]
        #: The source whose labelled objects copy-paste takes (None: no copy-paste).
        self.donor_source = donor_source
        #: The sources whose samples get pasted objects (None: all).
        self.paste_onto = paste_onto
        self.size_px = size_px
        self.ref_px = ref_px
        self.seed = seed
        self.augment = augment
        self.no_mosaic = replace(augment, mosaic_p=0.0)

    def __len__(self) -> int:
        return sum(len(c) for c in self.caches)

    def __getitem__(self, key: SampleKey) -> tuple[Tensor, Tensor]:
        epoch, source, i, draw, mosaic = key
        rng = np.random.default_rng([self.seed, epoch, source, i, draw])
        cfg = self.augment if mosaic else self.no_mosaic
        img, boxes = training_sample(
            self.caches[source],
            i,
            size_px=self.size_px,
            ref_px=self.ref_px,
            rng=rng,
            cfg=cfg,
            donors=self._donors(source),
        )
        return torch.from_numpy(img).permute(2, 0, 1).contiguous(), torch.from_numpy(boxes)

    def _donors(self, source: int) -> ImageCache | None:
        if self.donor_source is None or (self.paste_onto is not None and source not in self.paste_onto):
            return None
        return self.caches[self.donor_source]


def batch_shares(weights: list[float], batch_size: int) -> list[int]:
    """Images per batch of each source: ``weight / sum * batch`` rounded by largest remainder, each >= 1."""
    w = np.asarray(weights, np.float64)
    exact = w / w.sum() * batch_size
    counts = np.floor(exact).astype(int)
    for i in np.argsort(-(exact - counts), kind="stable")[: batch_size - int(counts.sum())]:
        counts[i] += 1
    while (counts == 0).any() and batch_size >= len(weights):
        counts[int(np.argmax(counts))] -= 1
        counts[int(np.argmin(counts))] += 1
    return [int(c) for c in counts]


class MixedBatchSampler(Sampler[list[SampleKey]]):
    """Batches with a fixed share of every source (:func:`batch_shares`), drawn from ``(seed, epoch)``.

    Each source is walked through in a fresh random order per pass; a small source is re-shuffled and walked
    again when it runs out (``draw`` in the key tells the passes apart), so every source is seen in its share
    whatever its size.
    """

    def __init__(self, sizes: list[int], weights: list[float], batch_size: int, batches: int, seed: int):
        if len(sizes) != len(weights) or not sizes:
            raise ValueError("one weight per source")
        total = sum(sizes)
        self.sizes = sizes
        self.batch_size = min(batch_size, total)
        self.shares = batch_shares(weights, self.batch_size)
        self.batches = max(1, batches)
        self.seed = seed
        self.epoch = 0
        self.mosaic = True

    def _stream(self, source: int, count: int) -> list[tuple[int, int]]:
        n = self.sizes[source]
        out: list[tuple[int, int]] = []
        draw = 0
        while len(out) < count:
            order = np.random.default_rng([self.seed, self.epoch, source, draw, 7]).permutation(n)
            out.extend((int(i), draw) for i in order[: count - len(out)])
            draw += 1
        return out

    def __iter__(self) -> Iterator[list[SampleKey]]:
        streams = [self._stream(s, k * self.batches) for s, k in enumerate(self.shares)]
        for b in range(self.batches):
            batch: list[SampleKey] = []
            for s, k in enumerate(self.shares):
                for i, draw in streams[s][b * k : (b + 1) * k]:
                    batch.append((self.epoch, s, i, draw, self.mosaic))
            yield batch

    def __len__(self) -> int:
        return self.batches


def collate(batch: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """Stack images; pad boxes to (B, M, 4) with a (B, M) mask."""
    images = torch.stack([b[0] for b in batch])
    m = max((len(b[1]) for b in batch), default=0)
    boxes = torch.zeros(len(batch), m, 4)
    mask = torch.zeros(len(batch), m, dtype=torch.bool)
    for i, (_, bx) in enumerate(batch):
        boxes[i, : len(bx)] = bx
        mask[i, : len(bx)] = True
    return images, boxes, mask


def worker_init(_: int) -> None:
    """A loader worker: one thread for OpenCV and torch (the workers are the parallelism)."""
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
