"""The leader detector networks: compact anchor-free single-class YOLO-style models (torch).

Two architectures share one output layout (per level, ``4 * reg_max`` box-distance logits and one leader
logit), so decoding, the loss and both runtimes serve either:

* ``shufflenetv2-fpn`` (:class:`ShuffleDet`, the default for new training): an ImageNet-pretrainable
  ShuffleNetV2 0.5x backbone, a light FPN neck (1x1 laterals, upsample-and-add, separable 3x3) and one
  separable 5x5 head conv per level; about 0.25 M parameters.
* ``leadernet`` (:class:`LeaderNet`), trained from scratch on renders.

Each lives in its own module (:mod:`~companion.perception.detector.shufflenet`,
:mod:`~companion.perception.detector.leadernet`, their shared layers in
:mod:`~companion.perception.detector.layers`); this one names them and builds either from a weights file.
"""

from __future__ import annotations

from typing import Any

from companion.perception.detector.leadernet import ARCH_LEADERNET, LeaderNet, ModelSpec
from companion.perception.detector.shufflenet import ARCH_SHUFFLE, ShuffleDet, ShuffleDetSpec

__all__ = [
    "ARCHITECTURES",
    "ARCH_LEADERNET",
    "ARCH_SHUFFLE",
    "DetectorNet",
    "DetectorSpec",
    "LeaderNet",
    "ModelSpec",
    "ShuffleDet",
    "ShuffleDetSpec",
    "arch_of",
    "build_net",
    "net_for_spec",
]

#: Architecture names stored in a weights file (a file without one is a LeaderNet).
ARCHITECTURES = (ARCH_LEADERNET, ARCH_SHUFFLE)

DetectorNet = LeaderNet | ShuffleDet
DetectorSpec = ModelSpec | ShuffleDetSpec


def build_net(arch: str, spec: dict[str, Any] | None = None) -> DetectorNet:
    """The network of ``arch`` with the spec of a weights file (defaults when None)."""
    if arch == ARCH_LEADERNET:
        return LeaderNet(ModelSpec.from_dict(spec) if spec is not None else None)
    if arch == ARCH_SHUFFLE:
        return ShuffleDet(ShuffleDetSpec.from_dict(spec) if spec is not None else None)
    raise ValueError(f"unknown detector architecture {arch!r} (known: {', '.join(ARCHITECTURES)})")


def net_for_spec(spec: DetectorSpec) -> DetectorNet:
    """The network a spec describes."""
    return ShuffleDet(spec) if isinstance(spec, ShuffleDetSpec) else LeaderNet(spec)


def arch_of(spec: DetectorSpec) -> str:
    """Architecture name of a spec."""
    return ARCH_SHUFFLE if isinstance(spec, ShuffleDetSpec) else ARCH_LEADERNET
