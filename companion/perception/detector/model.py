"""The leader detector networks: compact anchor-free single-class YOLO-style models (torch).

Two architectures share one output layout (per level, ``4 * reg_max`` box-distance logits and one leader
logit), so decoding, the loss and both runtimes serve either:

* ``shufflenetv2-fpn`` (:class:`ShuffleDet`, the default for new training): an ImageNet-pretrainable
  ShuffleNetV2 0.5x backbone, a light FPN neck (1x1 laterals, upsample-and-add, separable 3x3) and one
  separable 5x5 head conv per level; about 0.25 M parameters.
* ``leadernet`` (:class:`LeaderNet`), described below, trained from scratch on renders.

``LeaderNet``:

Backbone (strided convs + cross-stage-partial blocks, SPPF) -> PAN neck -> decoupled head per level
(box distances as a distribution over ``reg_max`` bins, DFL-style, and one objectness/class logit).
Strides 8, 16 and 32; the input is letterboxed to a multiple of 32 on each side. The default shape (about
1.0 M parameters, 0.19 G multiply-adds at 320x256) was picked by timing ONNX Runtime on 2 CPU cores: dense
3x3 stride-2 convs and a second head conv cost 30-40% more time for little capacity at this size.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

ARCH_LEADERNET = "leadernet"
ARCH_SHUFFLE = "shufflenetv2-fpn"


@dataclass(frozen=True)
class ModelSpec:
    """Hyper-parameters that fix the network's shape; stored with the weights."""

    #: Channels of the stem and of the four backbone stages (strides 2, 4, 8, 16, 32).
    widths: tuple[int, int, int, int, int] = (16, 32, 48, 96, 224)
    #: Bottleneck repeats in the CSP block of stages 2..5 (0: no block).
    depths: tuple[int, int, int, int] = (0, 1, 1, 1)
    #: Channels of the neck outputs at strides 8, 16, 32.
    neck_widths: tuple[int, int, int] = (32, 64, 112)
    #: Channels of the head branches and the number of 3x3 convs in each.
    head_width: int = 32
    head_convs: int = 1
    #: Downsample with depthwise-separable convs (cheaper) instead of dense 3x3 stride-2 convs.
    dw_down: bool = True
    #: Bins of the box-distance distribution (distances up to reg_max - 1 strides).
    reg_max: int = 16
    strides: tuple[int, int, int] = (8, 16, 32)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelSpec:
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**fields)


class ConvBnAct(nn.Module):
    """Conv (no bias) -> BatchNorm -> ReLU; BN folds into the conv for inference (:func:`fuse`)."""

    def __init__(
        self, c_in: int, c_out: int, k: int = 3, s: int = 1, *, groups: int = 1, act: bool = True
    ) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, groups=groups, bias=False)
        self.bn: nn.Module = nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.03)
        self.act: nn.Module = nn.ReLU(inplace=True) if act else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.bn(self.conv(x)))  # type: ignore[no-any-return]

    def fuse(self) -> None:
        """Fold BatchNorm into the convolution's weight and bias (inference only)."""
        if not isinstance(self.bn, nn.BatchNorm2d):
            return
        bn = self.bn
        if bn.running_var is None or bn.running_mean is None:
            raise RuntimeError("cannot fold a BatchNorm without running statistics")
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        fused = nn.Conv2d(
            self.conv.in_channels,
            self.conv.out_channels,
            self.conv.kernel_size,  # type: ignore[arg-type]
            self.conv.stride,  # type: ignore[arg-type]
            self.conv.padding,  # type: ignore[arg-type]
            groups=self.conv.groups,
            bias=True,
        ).to(self.conv.weight.device)
        with torch.no_grad():
            fused.weight.copy_(self.conv.weight * scale.reshape(-1, 1, 1, 1))
            fused.bias.copy_(bn.bias - bn.running_mean * scale)  # type: ignore[union-attr]
        self.conv = fused
        self.bn = nn.Identity()


class DownSample(nn.Module):
    """Stride-2 depthwise 3x3 then pointwise 1x1: a cheap downsampling that changes the width."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.dw = ConvBnAct(c_in, c_in, 3, 2, groups=c_in, act=False)
        self.pw = ConvBnAct(c_in, c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.pw(self.dw(x))  # type: ignore[no-any-return]


class Bottleneck(nn.Module):
    """Two 3x3 convs with a residual connection."""

    def __init__(self, c: int, shortcut: bool = True):
        super().__init__()
        self.cv1 = ConvBnAct(c, c, 3)
        self.cv2 = ConvBnAct(c, c, 3)
        self.shortcut = shortcut

    def forward(self, x: Tensor) -> Tensor:
        y: Tensor = self.cv2(self.cv1(x))
        return x + y if self.shortcut else y


class CSPBlock(nn.Module):
    """Cross-stage-partial block: split, run ``n`` bottlenecks on one half, concatenate every stage, mix."""

    def __init__(self, c_in: int, c_out: int, n: int, shortcut: bool = True):
        super().__init__()
        self.c_half = c_out // 2
        self.cv1 = ConvBnAct(c_in, 2 * self.c_half, 1)
        self.blocks = nn.ModuleList(Bottleneck(self.c_half, shortcut) for _ in range(n))
        self.cv2 = ConvBnAct((2 + n) * self.c_half, c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        y = list(self.cv1(x).chunk(2, 1))
        for block in self.blocks:
            y.append(block(y[-1]))
        return self.cv2(torch.cat(y, 1))  # type: ignore[no-any-return]


class SPPF(nn.Module):
    """Spatial pyramid pooling (fast): three chained 5x5 max-pools, concatenated."""

    def __init__(self, c: int):
        super().__init__()
        self.cv1 = ConvBnAct(c, c // 2, 1)
        self.cv2 = ConvBnAct(c // 2 * 4, c, 1)

    def forward(self, x: Tensor) -> Tensor:
        x = self.cv1(x)
        y1 = F.max_pool2d(x, 5, 1, 2)
        y2 = F.max_pool2d(y1, 5, 1, 2)
        y3 = F.max_pool2d(y2, 5, 1, 2)
        return self.cv2(torch.cat((x, y1, y2, y3), 1))  # type: ignore[no-any-return]


class Backbone(nn.Module):
    """Stem and four strided stages; returns the stride 8, 16 and 32 feature maps."""

    def __init__(self, spec: ModelSpec):
        super().__init__()
        w, d = spec.widths, spec.depths
        self.stem = ConvBnAct(3, w[0], 3, 2)

        def down(c_in: int, c_out: int) -> nn.Module:
            return DownSample(c_in, c_out) if spec.dw_down else ConvBnAct(c_in, c_out, 3, 2)

        def csp(c: int, n: int) -> list[nn.Module]:
            return [CSPBlock(c, c, n)] if n else []

        self.stage2 = nn.Sequential(down(w[0], w[1]), *csp(w[1], d[0]))
        self.stage3 = nn.Sequential(down(w[1], w[2]), *csp(w[2], d[1]))
        self.stage4 = nn.Sequential(down(w[2], w[3]), *csp(w[3], d[2]))
        self.stage5 = nn.Sequential(down(w[3], w[4]), *csp(w[4], d[3]), SPPF(w[4]))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c3 = self.stage3(self.stage2(self.stem(x)))
        c4 = self.stage4(c3)
        return c3, c4, self.stage5(c4)


class Neck(nn.Module):
    """Path-aggregation neck: top-down (upsample, concatenate) then bottom-up (strided conv, concatenate)."""

    def __init__(self, spec: ModelSpec):
        super().__init__()
        _, _, c3, c4, c5 = spec.widths
        n3, n4, n5 = spec.neck_widths
        self.td4 = CSPBlock(c5 + c4, n4, 1, shortcut=False)
        self.td3 = CSPBlock(n4 + c3, n3, 1, shortcut=False)
        self.down3 = ConvBnAct(n3, n3, 3, 2)
        self.bu4 = CSPBlock(n3 + n4, n4, 1, shortcut=False)
        self.down4 = ConvBnAct(n4, n4, 3, 2)
        self.bu5 = CSPBlock(n4 + c5, n5, 1, shortcut=False)

    def forward(self, feats: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        c3, c4, c5 = feats
        t4 = self.td4(
            torch.cat(
                (F.interpolate(c5, scale_factor=2.0, mode="nearest", recompute_scale_factor=False), c4), 1
            )
        )
        p3 = self.td3(
            torch.cat(
                (F.interpolate(t4, scale_factor=2.0, mode="nearest", recompute_scale_factor=False), c3), 1
            )
        )
        p4 = self.bu4(torch.cat((self.down3(p3), t4), 1))
        p5 = self.bu5(torch.cat((self.down4(p4), c5), 1))
        return p3, p4, p5


class HeadLevel(nn.Module):
    """Decoupled head of one level: a box branch (4 x reg_max logits) and a class branch (1 logit)."""

    def __init__(self, c_in: int, width: int, n_convs: int, reg_max: int, stride: int):
        super().__init__()

        def branch(c_out: int) -> nn.Sequential:
            convs = [ConvBnAct(c_in if i == 0 else width, width, 3) for i in range(n_convs)]
            return nn.Sequential(*convs, nn.Conv2d(width, c_out, 1))

        self.box = branch(4 * reg_max)
        self.cls = branch(1)
        self._init_bias(stride)

    def _init_bias(self, stride: int) -> None:
        # Start with a low foreground prior (about 1 object per 320x320 image) so early training is stable.
        cls_out, box_out = self.cls[-1], self.box[-1]
        if not isinstance(cls_out, nn.Conv2d) or not isinstance(box_out, nn.Conv2d):
            raise TypeError("head branches must end in a Conv2d")
        nn.init.constant_(cls_out.bias, float(torch.log(torch.tensor(1.0 / (320 / stride) ** 2))))  # type: ignore[arg-type]
        nn.init.constant_(box_out.bias, 1.0)  # type: ignore[arg-type]

    def forward(self, x: Tensor) -> Tensor:
        return torch.cat((self.box(x), self.cls(x)), 1)


class LeaderNet(nn.Module):
    """Backbone + neck + head. ``forward`` returns raw per-level maps (B, 4*reg_max+1, H/s, W/s)."""

    arch = ARCH_LEADERNET

    def __init__(self, spec: ModelSpec | None = None):
        super().__init__()
        self.spec = spec or ModelSpec()
        self.backbone = Backbone(self.spec)
        self.neck = Neck(self.spec)
        self.heads = nn.ModuleList(
            HeadLevel(c, self.spec.head_width, self.spec.head_convs, self.spec.reg_max, s)
            for c, s in zip(self.spec.neck_widths, self.spec.strides, strict=True)
        )

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = self.neck(self.backbone(x))
        return [head(f) for head, f in zip(self.heads, feats, strict=True)]

    def fuse(self) -> LeaderNet:
        """Fold every BatchNorm into its conv, in place (for inference and export); returns self."""
        for m in self.modules():
            if isinstance(m, ConvBnAct):
                m.fuse()
        return self


def count_parameters(module: nn.Module) -> int:
    """Number of parameters."""
    return sum(p.numel() for p in module.parameters())


# ----------------------------------------------------------------------------------------------------
# ShuffleNetV2 0.5x backbone with a light FPN neck (the ``shufflenetv2-fpn`` architecture).
# ----------------------------------------------------------------------------------------------------


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
                _fuse_sequential(m)
        return self


def _fold(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Conv2d:
    if bn.running_var is None or bn.running_mean is None:
        raise RuntimeError("cannot fold a BatchNorm without running statistics")
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    fused = nn.Conv2d(
        conv.in_channels,
        conv.out_channels,
        conv.kernel_size,  # type: ignore[arg-type]
        conv.stride,  # type: ignore[arg-type]
        conv.padding,  # type: ignore[arg-type]
        groups=conv.groups,
        bias=True,
    ).to(conv.weight.device)
    with torch.no_grad():
        fused.weight.copy_(conv.weight * scale.reshape(-1, 1, 1, 1))
        bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
        fused.bias.copy_(bn.bias + (bias - bn.running_mean) * scale)  # type: ignore[union-attr]
    return fused


def _fuse_sequential(seq: nn.Sequential) -> None:
    """Conv2d followed by BatchNorm2d in a Sequential: fold, and put an Identity where the BN was."""
    mods = list(seq)
    for i in range(len(mods) - 1):
        a, b = mods[i], mods[i + 1]
        if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
            seq[i] = _fold(a, b)
            seq[i + 1] = nn.Identity()


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
