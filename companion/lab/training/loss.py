"""Training loss: task-aligned label assignment, then classification (BCE), box (CIoU) and DFL terms.

Assignment follows the task-aligned idea (TOOD / YOLOv8): for each ground-truth box, the candidate cells whose
prediction is both confident and well placed (score^alpha * IoU^beta) become positives, the top ``top_k`` of
them; their soft target score is that alignment, rescaled so the best cell of each box gets its IoU.
Candidates are the cells whose centre lies inside the box *or* within ``center_radius`` strides of its centre,
so that a leader of a few pixels (smaller than a stride) still gets positives.

The box term can trust a sample's box less on size than on position (``size_weight`` per image): hand
labels of real video carry a margin that changes from video to video, so their centre is worth more than
their extent. CIoU's loss splits exactly into a position part (centre distance, and the IoU lost to the
offset) and a size part (the IoU of the box moved onto the label's centre, and the aspect term), and the
size part and the DFL edge distributions are scaled by the image's weight (1: plain CIoU and DFL).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional as F  # noqa: N812

from companion.perception.detector.model import DetectorNet

_EPS = 1e-9


@dataclass(frozen=True)
class LossConfig:
    """Weights of the loss terms and assigner settings."""

    box_gain: float = 7.5
    cls_gain: float = 0.5
    dfl_gain: float = 1.5
    top_k: int = 10
    alpha: float = 1.0
    beta: float = 6.0
    center_radius: float = 2.5


def anchor_points(feats: list[Tensor], strides: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    """Cell centres (A, 2) in input pixels and their strides (A, 1), level by level, row-major."""
    points, stride_col = [], []
    for f, s in zip(feats, strides, strict=True):
        h, w = f.shape[-2:]
        ys = (torch.arange(h, device=f.device, dtype=torch.float32) + 0.5) * s
        xs = (torch.arange(w, device=f.device, dtype=torch.float32) + 0.5) * s
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        points.append(torch.stack((gx, gy), -1).reshape(-1, 2))
        stride_col.append(torch.full((h * w, 1), float(s), device=f.device))
    return torch.cat(points), torch.cat(stride_col)


def flatten_levels(feats: list[Tensor]) -> Tensor:
    """Per-level maps (B, C, H, W) -> (B, A, C)."""
    return torch.cat([f.flatten(2) for f in feats], 2).transpose(1, 2)


def dfl_expectation(box_logits: Tensor, reg_max: int) -> Tensor:
    """(B, A, 4*reg_max) logits -> (B, A, 4) expected distances (ltrb) in strides."""
    b, a, _ = box_logits.shape
    prob = box_logits.reshape(b, a, 4, reg_max).softmax(-1)
    return prob @ torch.arange(reg_max, device=box_logits.device, dtype=prob.dtype)


def decode_boxes(points: Tensor, ltrb_px: Tensor) -> Tensor:
    """Anchor points (A, 2) and distances (B, A, 4) in pixels -> boxes (B, A, 4) x0 y0 x1 y1."""
    return torch.cat((points - ltrb_px[..., :2], points + ltrb_px[..., 2:]), -1)


def box_iou_pairwise(a: Tensor, b: Tensor) -> Tensor:
    """IoU of boxes ``a`` (..., 4) and ``b`` (..., 4), broadcasting, x0 y0 x1 y1."""
    iw = (torch.minimum(a[..., 2], b[..., 2]) - torch.maximum(a[..., 0], b[..., 0])).clamp(min=0)
    ih = (torch.minimum(a[..., 3], b[..., 3]) - torch.maximum(a[..., 1], b[..., 1])).clamp(min=0)
    inter = iw * ih
    area_a = (a[..., 2] - a[..., 0]).clamp(min=0) * (a[..., 3] - a[..., 1]).clamp(min=0)
    area_b = (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)
    return inter / (area_a + area_b - inter + _EPS)


def ciou_loss_parts(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``1 - CIoU`` of matched boxes (N, 4) split into (position, size) parts that sum to it.

    Size: ``1 - IoU`` of ``a`` moved onto ``b``'s centre, plus the aspect-ratio penalty. Position: the
    normalised centre distance plus the IoU the offset costs (centred IoU minus IoU, >= 0 for axis-aligned
    boxes, whose overlap is largest with coincident centres).
    """
    iou = box_iou_pairwise(a, b)
    shift = ((b[:, :2] + b[:, 2:]) - (a[:, :2] + a[:, 2:])) / 2
    centred = a + torch.cat((shift, shift), -1)
    iou_c = box_iou_pairwise(centred, b)
    cw = torch.maximum(a[:, 2], b[:, 2]) - torch.minimum(a[:, 0], b[:, 0])
    ch = torch.maximum(a[:, 3], b[:, 3]) - torch.minimum(a[:, 1], b[:, 1])
    c2 = cw**2 + ch**2 + _EPS
    rho2 = ((a[:, 0] + a[:, 2] - b[:, 0] - b[:, 2]) ** 2 + (a[:, 1] + a[:, 3] - b[:, 1] - b[:, 3]) ** 2) / 4
    wa, ha = a[:, 2] - a[:, 0], (a[:, 3] - a[:, 1]).clamp(min=_EPS)
    wb, hb = b[:, 2] - b[:, 0], (b[:, 3] - b[:, 1]).clamp(min=_EPS)
    v = (4 / torch.pi**2) * (torch.atan(wb / hb) - torch.atan(wa / ha)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + 1.0).clamp(min=1e-7)
    return rho2 / c2 + (iou_c - iou), (1.0 - iou_c) + v * alpha


def ciou(a: Tensor, b: Tensor) -> Tensor:
    """Complete IoU of matched boxes (N, 4): IoU minus centre-distance and aspect-ratio penalties."""
    iou = box_iou_pairwise(a, b)
    cw = torch.maximum(a[:, 2], b[:, 2]) - torch.minimum(a[:, 0], b[:, 0])
    ch = torch.maximum(a[:, 3], b[:, 3]) - torch.minimum(a[:, 1], b[:, 1])
    c2 = cw**2 + ch**2 + _EPS
    rho2 = ((a[:, 0] + a[:, 2] - b[:, 0] - b[:, 2]) ** 2 + (a[:, 1] + a[:, 3] - b[:, 1] - b[:, 3]) ** 2) / 4
    wa, ha = a[:, 2] - a[:, 0], (a[:, 3] - a[:, 1]).clamp(min=_EPS)
    wb, hb = b[:, 2] - b[:, 0], (b[:, 3] - b[:, 1]).clamp(min=_EPS)
    v = (4 / torch.pi**2) * (torch.atan(wb / hb) - torch.atan(wa / ha)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + 1.0).clamp(min=1e-7)
    return iou - (rho2 / c2 + v * alpha)


@dataclass
class Assignment:
    """Per-cell targets of one batch."""

    fg_mask: Tensor  # (B, A) bool
    target_boxes: Tensor  # (B, A, 4) px
    target_scores: Tensor  # (B, A) soft score in [0, 1]


@torch.no_grad()
def assign(
    pred_scores: Tensor,
    pred_boxes: Tensor,
    *,
    points: Tensor,
    stride_col: Tensor,
    gt_boxes: Tensor,
    gt_mask: Tensor,
    cfg: LossConfig,
) -> Assignment:
    """Task-aligned assignment.

    Args:
        pred_scores: (B, A) sigmoid scores.
        pred_boxes: (B, A, 4) predicted boxes, px.
        points: (A, 2) cell centres, px.
        stride_col: (A, 1) stride of each cell, px.
        gt_boxes: (B, M, 4) ground truth, px, padded.
        gt_mask: (B, M) marks the real ground-truth rows.
        cfg: assigner settings.
    """
    b, a = pred_scores.shape
    m = gt_boxes.shape[1]
    dev = pred_scores.device
    if m == 0 or not bool(gt_mask.any()):
        return Assignment(
            torch.zeros(b, a, dtype=torch.bool, device=dev),
            torch.zeros(b, a, 4, device=dev),
            torch.zeros(b, a, device=dev),
        )
    px, py = points[:, 0].view(1, 1, a), points[:, 1].view(1, 1, a)
    g = gt_boxes.unsqueeze(2)  # (B, M, 1, 4)
    inside = (px > g[..., 0]) & (px < g[..., 2]) & (py > g[..., 1]) & (py < g[..., 3])
    gcx, gcy = (g[..., 0] + g[..., 2]) / 2, (g[..., 1] + g[..., 3]) / 2
    r = cfg.center_radius * stride_col.view(1, 1, a)
    near = ((px - gcx).abs() < r) & ((py - gcy).abs() < r)
    candidate = (inside | near) & gt_mask.unsqueeze(2)  # (B, M, A)

    iou = box_iou_pairwise(pred_boxes.unsqueeze(1), g).clamp(min=0)  # (B, M, A)
    iou = iou * candidate
    align = pred_scores.unsqueeze(1).clamp(min=0) ** cfg.alpha * iou**cfg.beta
    align = align * candidate
    k = min(cfg.top_k, a)
    top_idx = align.topk(k, dim=-1).indices  # (B, M, k)
    top = torch.zeros_like(candidate)
    top.scatter_(-1, top_idx, True)
    pos = top & candidate  # (B, M, A)

    # A cell claimed by several boxes goes to the one it overlaps most.
    multi = pos.sum(1, keepdim=True) > 1
    if bool(multi.any()):
        best = iou.argmax(1, keepdim=True)  # (B, 1, A)
        only_best = torch.zeros_like(pos).scatter_(1, best, True)
        pos = torch.where(multi, only_best & candidate, pos)
    fg = pos.any(1)  # (B, A)
    gt_idx = pos.float().argmax(1)  # (B, A)
    target_boxes = torch.gather(gt_boxes, 1, gt_idx.unsqueeze(-1).expand(b, a, 4))

    align = align * pos
    max_align = align.amax(-1, keepdim=True)
    max_iou = (iou * pos).amax(-1, keepdim=True)
    norm = (align * max_iou / (max_align + _EPS)).amax(1)  # (B, A)
    return Assignment(fg, target_boxes, norm * fg)


def dfl_loss(box_logits: Tensor, target_ltrb: Tensor, reg_max: int) -> Tensor:
    """Distribution focal loss per cell (N,): cross-entropy on the two bins either side of the target."""
    t = target_ltrb.clamp(0, reg_max - 1 - 0.01)
    left = t.long()
    w_right = t - left
    logits = box_logits.reshape(-1, reg_max)
    ce_l = F.cross_entropy(logits, left.reshape(-1), reduction="none").view(left.shape)
    ce_r = F.cross_entropy(logits, (left + 1).reshape(-1), reduction="none").view(left.shape)
    return (ce_l * (1 - w_right) + ce_r * w_right).mean(-1)


class DetectionLoss:
    """Loss of a batch: raw level maps + padded ground truth -> (total, parts for logging)."""

    def __init__(self, net: DetectorNet, cfg: LossConfig | None = None) -> None:
        self.cfg = cfg or LossConfig()
        self.reg_max = net.spec.reg_max
        self.strides = net.spec.strides

    def __call__(
        self, feats: list[Tensor], gt_boxes: Tensor, gt_mask: Tensor, size_weight: Tensor | None = None
    ) -> tuple[Tensor, dict[str, float]]:
        """``size_weight`` (B,): per image, the weight of the box's size part and DFL (None: all 1)."""
        points, stride_col = anchor_points(feats, self.strides)
        flat = flatten_levels(feats).float()
        box_logits, cls_logits = flat[..., :-1], flat[..., -1]
        ltrb = dfl_expectation(box_logits, self.reg_max)
        pred_boxes = decode_boxes(points, ltrb * stride_col)
        asg = assign(
            cls_logits.sigmoid().detach(),
            pred_boxes.detach(),
            points=points,
            stride_col=stride_col,
            gt_boxes=gt_boxes,
            gt_mask=gt_mask,
            cfg=self.cfg,
        )
        score_sum = asg.target_scores.sum().clamp(min=1.0)
        loss_cls = (
            F.binary_cross_entropy_with_logits(cls_logits, asg.target_scores, reduction="sum") / score_sum
        )
        fg = asg.fg_mask
        if bool(fg.any()):
            w = asg.target_scores[fg]
            if size_weight is None:
                loss_box = ((1.0 - ciou(pred_boxes[fg], asg.target_boxes[fg])) * w).sum() / score_sum
                w_edges = w
            else:
                sw = size_weight.to(w.dtype).unsqueeze(1).expand_as(fg)[fg]
                position, size = ciou_loss_parts(pred_boxes[fg], asg.target_boxes[fg])
                loss_box = ((position + sw * size) * w).sum() / score_sum
                w_edges = w * sw
            pts = points.unsqueeze(0).expand_as(pred_boxes[..., :2])[fg]
            st = stride_col.unsqueeze(0).expand(fg.shape[0], -1, -1)[fg]
            tb = asg.target_boxes[fg]
            target_ltrb = torch.cat((pts - tb[:, :2], tb[:, 2:] - pts), -1) / st
            loss_dfl = (dfl_loss(box_logits[fg], target_ltrb, self.reg_max) * w_edges).sum() / score_sum
        else:
            loss_box = flat.sum() * 0.0
            loss_dfl = flat.sum() * 0.0
        c = self.cfg
        total = c.box_gain * loss_box + c.cls_gain * loss_cls + c.dfl_gain * loss_dfl
        parts = {
            "box": float(loss_box.detach()),
            "cls": float(loss_cls.detach()),
            "dfl": float(loss_dfl.detach()),
        }
        return total, parts
