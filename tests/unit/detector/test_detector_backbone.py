"""The ShuffleNetV2 backbone and the shufflenetv2-fpn network: layout, pretrained loading, fusion, files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from companion.kernel.errors import ModelError
from companion.perception.detector.layers import count_parameters
from companion.perception.detector.leadernet import LeaderNet
from companion.perception.detector.model import build_net
from companion.perception.detector.shufflenet import (
    ARCH_SHUFFLE,
    ShuffleDet,
    ShuffleDetSpec,
    ShuffleV2Block,
    load_backbone,
)
from companion.perception.detector.torch_engine import load_weights, save_weights

PRETRAINED = (
    Path(__file__).resolve().parents[4] / "shared" / "weights" / "shufflenetv2-0.5x" / "shufflenetv2.pth"
)
SMALL = ShuffleDetSpec(neck_width=16)


def _megvii_shuffle(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # The reference implementation's channel_shuffle, verbatim in its steps.
    b, c, h, w = x.shape
    x = x.reshape(b * c // 2, 2, h * w).permute(1, 0, 2).reshape(2, -1, c // 2, h, w)
    return x[0], x[1]


def test_channel_split_matches_the_reference_shuffle() -> None:
    x = torch.randn(2, 8, 3, 5)
    ours = ShuffleV2Block.channel_split(x)
    ref = _megvii_shuffle(x)
    for a, b in zip(ours, ref, strict=True):
        torch.testing.assert_close(a, b)


def test_backbone_layout_and_stage_outputs() -> None:
    net = ShuffleDet(SMALL).eval()
    names = set(net.backbone.state_dict())
    assert "first_conv.0.weight" in names
    assert "stage2.0.branch_proj.2.weight" in names
    assert "stage3.7.branch_main.5.weight" in names
    assert not any(k.startswith("stage2.1.branch_proj") for k in names)
    c3, c4, c5 = net.backbone(torch.zeros(1, 3, 64, 96))
    assert c3.shape == (1, 48, 8, 12)
    assert c4.shape == (1, 96, 4, 6)
    assert c5.shape == (1, 192, 2, 3)
    levels = net(torch.zeros(1, 3, 64, 96))
    assert [tuple(o.shape) for o in levels] == [(1, 65, 8, 12), (1, 65, 4, 6), (1, 65, 2, 3)]


@pytest.mark.skipif(not PRETRAINED.exists(), reason="shared pretrained weights not on this machine")
def test_pretrained_weights_load_strictly_with_rgb_input() -> None:
    net = ShuffleDet()
    load_backbone(net.backbone, PRETRAINED)
    raw = torch.load(PRETRAINED, map_location="cpu", weights_only=True)
    ours = net.backbone.state_dict()
    assert set(ours) == set(raw)
    torch.testing.assert_close(ours["first_conv.0.weight"], raw["first_conv.0.weight"].flip(1))
    torch.testing.assert_close(ours["stage4.3.branch_main.5.weight"], raw["stage4.3.branch_main.5.weight"])
    # The RGB network on an RGB image computes what the pretrained network computes on the BGR image.
    bgr_net = ShuffleDet()
    load_backbone(bgr_net.backbone, PRETRAINED, rgb_input=False)
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        a = net.backbone.eval()(x)
        b = bgr_net.backbone.eval()(x.flip(1))
    for fa, fb in zip(a, b, strict=True):
        torch.testing.assert_close(fa, fb, atol=1e-4, rtol=1e-4)
    assert count_parameters(net.backbone) == 143_136


def test_fuse_keeps_the_outputs() -> None:
    torch.manual_seed(0)
    net = ShuffleDet(SMALL)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                assert m.running_mean is not None
                assert m.running_var is not None
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    net.eval()
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        before = [o.clone() for o in net(x)]
        net.fuse()
        after = net(x)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    for a, b in zip(before, after, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_weights_file_names_its_architecture(tmp_path: Path) -> None:
    net = ShuffleDet(SMALL)
    save_weights(tmp_path / "s.pt", net, 320, {"note": "test"})
    loaded, size, meta = load_weights(tmp_path / "s.pt")
    assert isinstance(loaded, ShuffleDet)
    assert loaded.spec == SMALL
    assert size == 320
    assert meta == {"note": "test"}
    # A file without an architecture name is the older network.
    old = LeaderNet()
    save_weights(tmp_path / "o.pt", old, 320, {})
    blob = torch.load(tmp_path / "o.pt", weights_only=True)
    del blob["arch"]
    torch.save(blob, tmp_path / "o.pt")
    assert isinstance(load_weights(tmp_path / "o.pt")[0], LeaderNet)
    blob["arch"] = "nonesuch"
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(ModelError, match="unknown detector architecture"):
        load_weights(tmp_path / "bad.pt")
    assert isinstance(build_net(ARCH_SHUFFLE), ShuffleDet)


@pytest.mark.slow
def test_onnx_export_matches_torch(tmp_path: Path) -> None:
    from companion.lab.training.export import export_and_sign, max_output_difference

    torch.manual_seed(1)
    pt = tmp_path / "leader_detector.pt"
    save_weights(pt, ShuffleDet(SMALL), 320, {})
    onnx_path, side = export_and_sign(pt)
    assert side.read_text().count("\n") == 2
    x = np.random.default_rng(0).random((1, 3, 64, 96), dtype=np.float32)
    assert max_output_difference(pt, onnx_path, [x]) < 1e-3
