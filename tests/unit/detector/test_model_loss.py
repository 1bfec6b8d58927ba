from __future__ import annotations

import pytest
import torch

from companion.lab.training.loss import (
    DetectionLoss,
    LossConfig,
    anchor_points,
    assign,
    box_iou_pairwise,
    ciou,
)
from companion.perception.detector.layers import count_parameters
from companion.perception.detector.leadernet import LeaderNet, ModelSpec

torch.set_num_threads(2)


def test_default_network_size_and_output_shapes() -> None:
    net = LeaderNet().eval()
    assert 0.9e6 <= count_parameters(net) <= 3e6
    out = net(torch.zeros(1, 3, 256, 320))
    assert [tuple(o.shape) for o in out] == [(1, 65, 32, 40), (1, 65, 16, 20), (1, 65, 8, 10)]


def test_folding_batchnorm_keeps_outputs() -> None:
    torch.manual_seed(1)
    net = LeaderNet(ModelSpec(widths=(16, 16, 32, 32, 64), neck_widths=(16, 32, 64), head_width=16)).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)  # type: ignore[union-attr]
                m.running_var.uniform_(0.5, 2.0)  # type: ignore[union-attr]
        x = torch.rand(2, 3, 128, 96)
        before = net(x)
        after = net.fuse()(x)
    for a, b in zip(before, after, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_ciou_of_identical_boxes_is_one_and_penalises_offsets() -> None:
    a = torch.tensor([[0.0, 0.0, 10.0, 10.0]])
    assert float(ciou(a, a)) == pytest.approx(1.0, abs=1e-6)
    shifted = a + torch.tensor([[5.0, 0.0, 5.0, 0.0]])
    assert float(ciou(a, shifted)) < float(box_iou_pairwise(a, shifted))


def _feats(h: int, w: int) -> list[torch.Tensor]:
    return [torch.zeros(1, 1, h // s, w // s) for s in (8, 16, 32)]


def test_a_box_smaller_than_a_stride_still_gets_positives() -> None:
    points, strides = anchor_points(_feats(128, 128), (8, 16, 32))
    a = points.shape[0]
    gt = torch.tensor([[[61.0, 61.0, 65.0, 64.0]]])  # 4 x 3 px, between cell centres
    pred = torch.cat((points - 3.0, points + 3.0), 1).unsqueeze(0)  # 6 px boxes everywhere
    asg = assign(
        torch.full((1, a), 0.5),
        pred,
        points=points,
        stride_col=strides,
        gt_boxes=gt,
        gt_mask=torch.ones(1, 1, dtype=torch.bool),
        cfg=LossConfig(),
    )
    assert int(asg.fg_mask.sum()) >= 1
    assert float(asg.target_scores.max()) > 0
    torch.testing.assert_close(asg.target_boxes[asg.fg_mask][0], gt[0, 0])


def test_overlapping_claims_resolve_to_the_best_overlap() -> None:
    points, strides = anchor_points(_feats(64, 64), (8, 16, 32))
    a = points.shape[0]
    pred = torch.cat((points - 8.0, points + 8.0), 1).unsqueeze(0)
    gt = torch.tensor([[[16.0, 16.0, 48.0, 48.0], [20.0, 20.0, 44.0, 44.0]]])
    asg = assign(
        torch.full((1, a), 0.5),
        pred,
        points=points,
        stride_col=strides,
        gt_boxes=gt,
        gt_mask=torch.ones(1, 2, dtype=torch.bool),
        cfg=LossConfig(),
    )
    assert asg.fg_mask.any()
    # each positive cell holds exactly one of the two boxes
    tb = asg.target_boxes[asg.fg_mask]
    assert all(any(torch.equal(t, g) for g in gt[0]) for t in tb)


def test_loss_is_finite_with_and_without_leaders_and_backpropagates() -> None:
    torch.manual_seed(0)
    net = LeaderNet()
    crit = DetectionLoss(net)
    feats = net(torch.rand(2, 3, 96, 96))
    boxes = torch.tensor([[[10.0, 10.0, 40.0, 30.0]], [[0.0, 0.0, 0.0, 0.0]]])
    mask = torch.tensor([[True], [False]])
    loss, parts = crit(feats, boxes, mask)
    assert torch.isfinite(loss)
    assert set(parts) == {"box", "cls", "dfl"}
    loss.backward()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)
    empty, parts = crit(
        net(torch.rand(1, 3, 64, 64)), torch.zeros(1, 0, 4), torch.zeros(1, 0, dtype=torch.bool)
    )
    assert torch.isfinite(empty)
    assert parts["box"] == 0.0
