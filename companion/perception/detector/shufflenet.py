"""``shufflenetv2-fpn`` (:class:`ShuffleDet`): ShuffleNetV2 0.5x backbone with a light FPN neck (torch).

An ImageNet-pretrainable ShuffleNetV2 0.5x backbone (:func:`load_backbone`), a light FPN neck (1x1
laterals, upsample-and-add, separable 3x3) and one separable 5x5 head conv per level; about 0.25 M
parameters. Its output maps have :class:`~companion.perception.detector.leadernet.LeaderNet`'s layout.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from companion.perception.detector.layers import ConvBnAct, fuse_sequential

ARCH_SHUFFLE = "shufflenetv2-fpn"


@dataclass(frozen=True)
class ShuffleDetSpec:
    """Shape of a :class:`ShuffleDet`; stored with the weights."""

    #: Output channels of ShuffleNetV2 stages 2-4 (0.5x: 48, 96, 192) and the stem width (24).
    stage_widths: tuple[int, int, int] = (48, 96, 192)
    stem_width: int = 24
    stage_repeats: tuple[int, int, int] = (4, 8, 4)
    #: Channels of the neck and head at every level.
    neck_width: int = 64
    #: Depthwise kernel of the head (5: a wider view of the context for a few extra multiply-adds).
    head_kernel: int = 5
    reg_max: int = 16
    strides: tuple[int, int, int] = (8, 16, 32)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ShuffleDetSpec:
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**fields)


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c)


class ShuffleV2Block(nn.Module):
    """A ShuffleNetV2 unit in the layout of Megvii's reference implementation (names match its weights).

    Stride 1: channel shuffle (even channels pass through, odd ones go through ``branch_main``), concatenate.
    Stride 2: ``branch_proj`` (depthwise stride-2 + pointwise) on the whole input beside ``branch_main``.
    """

    def __init__(self, c_in: int, c_out: int, c_mid: int, stride: int) -> None:
        super().__init__()
        self.stride = stride
        c_main = c_out - c_in
        self.branch_main = nn.Sequential(
            nn.Conv2d(c_in, c_mid, 1, 1, 0, bias=False),
            _bn(c_mid),
            nn.ReLU(inplace=True),
            nn.Conv2d(c_mid, c_mid, 3, stride, 1, groups=c_mid, bias=False),
            _bn(c_mid),
            nn.Conv2d(c_mid, c_main, 1, 1, 0, bias=False),
            _bn(c_main),
            nn.ReLU(inplace=True),
        )
        self.branch_proj: nn.Module | None = None
        if stride == 2:
            self.branch_proj = nn.Sequential(
                nn.Conv2d(c_in, c_in, 3, stride, 1, groups=c_in, bias=False),
                _bn(c_in),
                nn.Conv2d(c_in, c_in, 1, 1, 0, bias=False),
                _bn(c_in),
                nn.ReLU(inplace=True),
            )

    @staticmethod
    def channel_split(x: Tensor) -> tuple[Tensor, Tensor]:
        """Even channels, odd channels (the reference implementation's shuffle before a stride-1 unit)."""
        b, c, h, w = x.shape
        y = x.reshape(b, c // 2, 2, h, w)
        return y[:, :, 0], y[:, :, 1]

    def forward(self, x: Tensor) -> Tensor:
        if self.branch_proj is not None:
            return torch.cat((self.branch_proj(x), self.branch_main(x)), 1)
        keep, work = self.channel_split(x)
        return torch.cat((keep, self.branch_main(work)), 1)


class ShuffleNetV2(nn.Module):
    """The ShuffleNetV2 feature extractor without its classifier; returns stride 8, 16 and 32 maps.

    Parameter names and shapes match ``shufflenetv2.pth`` (0.5x), loadable with ``strict=True``.
    """

    def __init__(self, spec: ShuffleDetSpec) -> None:
        super().__init__()
        c0 = spec.stem_width
        self.first_conv = nn.Sequential(nn.Conv2d(3, c0, 3, 2, 1, bias=False), _bn(c0), nn.ReLU(inplace=True))
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        stages: list[nn.Sequential] = []
        c_in = c0
        for c_out, n in zip(spec.stage_widths, spec.stage_repeats, strict=True):
            blocks = [ShuffleV2Block(c_in, c_out, c_out // 2, 2)]
            blocks += [ShuffleV2Block(c_out // 2, c_out, c_out // 2, 1) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            c_in = c_out
        self.stage2, self.stage3, self.stage4 = stages

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c3 = self.stage2(self.maxpool(self.first_conv(x)))
        c4 = self.stage3(c3)
        return c3, c4, self.stage4(c4)


def load_backbone(backbone: ShuffleNetV2, path: str | Path, *, rgb_input: bool = True) -> None:
    """Load pretrained ShuffleNetV2 weights (a plain state dict) with ``strict=True``.

    The pretrained network expects BGR / 255; the detector is fed RGB / 255 (as every Wingman runtime), so
    the first convolution's input channels are reversed when ``rgb_input`` (the same function, RGB in).
    """
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ValueError(f"{path} is not a state dict")
    state = dict(state)
    if rgb_input:
        state["first_conv.0.weight"] = state["first_conv.0.weight"].flip(1).contiguous()
    backbone.load_state_dict(state, strict=True)


class SepConv(nn.Module):
    """Depthwise k x k (BN) then pointwise 1x1 (BN, ReLU)."""

    def __init__(self, c_in: int, c_out: int, k: int = 3) -> None:
        super().__init__()
        self.dw = ConvBnAct(c_in, c_in, k, 1, groups=c_in, act=False)
        self.pw = ConvBnAct(c_in, c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.pw(self.dw(x))  # type: ignore[no-any-return]


class LightFPN(nn.Module):
    """1x1 laterals to one width, top-down upsample-and-add, one separable 3x3 per level."""

    def __init__(self, spec: ShuffleDetSpec) -> None:
        super().__init__()
        c = spec.neck_width
        self.lateral = nn.ModuleList(ConvBnAct(w, c, 1) for w in spec.stage_widths)
        self.smooth = nn.ModuleList(SepConv(c, c, 3) for _ in spec.stage_widths)

    def forward(self, feats: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        l3, l4, l5 = (lat(f) for lat, f in zip(self.lateral, feats, strict=True))
        p5 = l5
        p4 = l4 + F.interpolate(p5, scale_factor=2.0, mode="nearest", recompute_scale_factor=False)
        p3 = l3 + F.interpolate(p4, scale_factor=2.0, mode="nearest", recompute_scale_factor=False)
        s3, s4, s5 = self.smooth
        return s3(p3), s4(p4), s5(p5)


class LightHead(nn.Module):
    """One level: a separable k x k conv shared by both outputs, then 1x1 to box logits and a leader logit."""

    def __init__(self, c: int, k: int, reg_max: int, stride: int) -> None:
        super().__init__()
        self.stem = SepConv(c, c, k)
        self.box = nn.Conv2d(c, 4 * reg_max, 1)
        self.cls = nn.Conv2d(c, 1, 1)
        nn.init.constant_(self.cls.bias, math.log(1.0 / (320 / stride) ** 2))  # type: ignore[arg-type]
        nn.init.constant_(self.box.bias, 1.0)  # type: ignore[arg-type]

    def forward(self, x: Tensor) -> Tensor:
        y = self.stem(x)
        return torch.cat((self.box(y), self.cls(y)), 1)


class ShuffleDet(nn.Module):
    """ShuffleNetV2 0.5x + light FPN + per-level heads; the output maps have :class:`LeaderNet`'s layout."""

    arch = ARCH_SHUFFLE

    def __init__(self, spec: ShuffleDetSpec | None = None) -> None:
        super().__init__()
        self.spec = spec or ShuffleDetSpec()
        self.backbone = ShuffleNetV2(self.spec)
        self.neck = LightFPN(self.spec)
        self.heads = nn.ModuleList(
            LightHead(self.spec.neck_width, self.spec.head_kernel, self.spec.reg_max, s)
            for s in self.spec.strides
        )

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = self.neck(self.backbone(x))
        return [head(f) for head, f in zip(self.heads, feats, strict=True)]

    def fuse(self) -> ShuffleDet:
        """Fold every BatchNorm into the convolution before it, in place (inference, export); returns self."""
        for m in self.modules():
            if isinstance(m, ConvBnAct):
                m.fuse()
            elif isinstance(m, nn.Sequential):
                fuse_sequential(m)
        return self
