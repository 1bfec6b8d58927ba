"""What defines a detector training run: :class:`TrainConfig` (saved in every checkpoint) and its datasets.

``--data [NAME=]DIR[:WEIGHT]`` names one :class:`DataSource` (:func:`parse_source`); see
:mod:`companion.lab.training.train` for how they mix.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from companion.lab.training.augment import AugmentConfig
from companion.lab.training.loss import LossConfig
from companion.perception.detector.model import DetectorSpec, arch_of
from companion.perception.detector.shufflenet import ShuffleDetSpec


def default_crop_px(input_size_px: int) -> int:
    """The training crop for an input size, px: 0.8x on the stride's grid (320 -> 256, 416 -> 320)."""
    return max(32, min(input_size_px, round(0.8 * input_size_px / 32) * 32))


@dataclass(frozen=True)
class DataSource:
    """One training dataset: a name (for the logs), its folder and its share of every batch."""

    name: str
    path: str
    weight: float = 1.0


def parse_source(text: str) -> DataSource:
    """``[NAME=]DIR[:WEIGHT]`` -> a :class:`DataSource` (name: the folder's name; weight: 1)."""
    name, sep, rest = text.partition("=")
    if not sep or "/" in name:
        name, rest = "", text
    path, weight = rest, 1.0
    head, colon, tail = rest.rpartition(":")
    if colon:
        try:
            weight = float(tail)
            path = head
        except ValueError:
            pass
    if weight <= 0 or not math.isfinite(weight):
        raise ValueError(f"--data {text}: the weight must be > 0")
    return DataSource(name or Path(path).name, path, weight)


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved in every checkpoint)."""

    data: str
    out: str
    #: Datasets mixed in every batch; empty: ``data`` alone.
    sources: tuple[DataSource, ...] = ()
    #: Share of the recordings of a flat folder (no ``train``/``val`` splits) held out for validation.
    holdout_fraction: float = 0.1
    #: Images per epoch (0: the sum of the sources' training images).
    epoch_images: int = 0
    #: Pretrained ShuffleNetV2 backbone weights (``shufflenetv2-fpn`` only; empty: random initialisation).
    backbone_weights: str = ""
    epochs: int = 30
    batch_size: int = 32
    input_size_px: int = 320
    #: Training images are crops of this size from frames scaled as at ``input_size_px`` (about 40% less
    #: CPU per image than whole 320 px mosaics; the network is fully convolutional); see default_crop_px.
    crop_px: int = 256
    lr: float = 2e-3
    final_lr_fraction: float = 0.05
    weight_decay: float = 0.05
    warmup_epochs: float = 2.0
    ema_decay: float = 0.999
    #: Mosaic is switched off for the last epochs so the model ends on whole frames, as at run time.
    close_mosaic_epochs: int = 5
    seed: int = 0
    workers: int = 1
    device: str = "auto"
    threads: int = 2
    train_split: str = "train"
    val_split: str = "val"
    val_every: int = 3
    max_val_images: int = 600
    #: Limit the training images (0: all); for smoke tests.
    max_train_images: int = 0
    #: Start a new run from these weights (a shipped ``.pt`` or a run's checkpoint; its EMA is taken),
    #: e.g. to fine-tune on a larger dataset. Empty: random initialisation.
    init_weights: str = ""
    #: The source whose labelled objects copy-paste takes (``augment.paste_p``); empty: no copy-paste.
    paste_from: str = ""
    #: The sources whose samples get pasted objects; empty: every source.
    paste_onto: tuple[str, ...] = ()
    #: (source name, weight) pairs: the weight of the size part of the box loss for that source's images
    #: (:mod:`companion.lab.training.loss`), below 1 for loosely labelled sources; unnamed sources: 1.
    size_weights: tuple[tuple[str, float], ...] = ()
    spec: DetectorSpec = field(default_factory=ShuffleDetSpec)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    @property
    def all_sources(self) -> tuple[DataSource, ...]:
        return self.sources or (DataSource(Path(self.data).name or "data", self.data, 1.0),)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["spec"] = self.spec.to_dict()
        d["arch"] = arch_of(self.spec)
        return d
