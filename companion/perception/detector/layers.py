"""Layers both detector networks share, BatchNorm folding for inference, and a parameter count (torch)."""

from __future__ import annotations

import torch
from torch import Tensor, nn


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


def fold_bn(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Conv2d:
    """A convolution with the BatchNorm after it folded in (inference only)."""
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


def fuse_sequential(seq: nn.Sequential) -> None:
    """Conv2d followed by BatchNorm2d in a Sequential: fold, and put an Identity where the BN was."""
    mods = list(seq)
    for i in range(len(mods) - 1):
        a, b = mods[i], mods[i + 1]
        if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
            seq[i] = fold_bn(a, b)
            seq[i + 1] = nn.Identity()


def count_parameters(module: nn.Module) -> int:
    """Number of parameters."""
    return sum(p.numel() for p in module.parameters())
