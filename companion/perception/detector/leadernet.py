"""``leadernet`` (:class:`LeaderNet`): the detector network trained from scratch on renders (torch).

Backbone (strided convs + cross-stage-partial blocks, SPPF) -> PAN neck -> decoupled head per level
(box distances as a distribution over ``reg_max`` bins, DFL-style, and one objectness/class logit).
Strides 8, 16 and 32; the input is letterboxed to a multiple of 32 on each side. The default shape (about
1.0 M parameters, 0.19 G multiply-adds at 320x256) was picked by timing ONNX Runtime on 2 CPU cores: dense
3x3 stride-2 convs and a second head conv cost 30-40% more time for little capacity at this size.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from companion.perception.detector.layers import ConvBnAct

ARCH_LEADERNET = "leadernet"


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
