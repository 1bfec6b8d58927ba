"""Auto-labels: the leader's box in a frame from where the leader says it is, confirmed by the depth image.

While GPS is healthy the follower knows where its leader is without looking: the leader's shared position,
the follower's own pose and the camera's mounting place the leader in the camera frame. That guess is off by
both vehicles' GPS errors and the share's age (often half a metre: tens of pixels at formation range), so it
is not a label yet. The depth image settles it: the leader is the blob of pixels at the expected range near
the expected place. Its box is the label; the agreement between guess and blob is its quality.

A frame is

* ``label``: one blob at the expected range, near the projection, of about the expected size;
* ``negative``: the leader is clearly outside the field of view (a drone-free frame, kept as a negative);
* ``rejected``: anything in between (no blob at the range, a blob that runs into the background, two
  candidates, the leader at the image edge, size or place disagreeing): never written as a label.

Pure: arrays and numbers in, an :class:`AutoLabel` out. Camera frame: x right, y down, z forward, m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np

from companion.kernel.camera import DepthImage, Intrinsics
from companion.kernel.frames import Mat3, Vec3
from companion.perception.transform import CameraGeometry

BoxT = tuple[float, float, float, float]


class Verdict(Enum):
    """What a frame is to the dataset."""

    LABEL = "label"
    NEGATIVE = "negative"
    REJECTED = "rejected"


@dataclass(frozen=True, slots=True)
class AutoLabelConfig:
    """How strict the labeller is.

    ``position_sigma_m`` is the 1-sigma error of the expected leader position (both GPS fixes and the
    share's age together); the search window reaches 3 sigma around the projection.
    """

    leader_span_m: float = 0.45
    position_sigma_m: float = 0.5
    #: Depth within max(abs, rel * range) + span of the expected range counts as the leader.
    depth_tol_abs_m: float = 0.6
    depth_tol_rel: float = 0.12
    min_range_m: float = 1.0
    max_range_m: float = 20.0
    #: A blob smaller than this share of the expected box area (or 6 px) is noise.
    min_blob_fraction: float = 0.04
    #: Measured box size over expected size outside [1/k, k]: rejected.
    max_size_ratio: float = 2.5
    #: Labels below this quality are rejected.
    min_quality: float = 0.35
    #: A second blob at least this share of the best one's area makes the frame ambiguous.
    rival_fraction: float = 0.5
    #: Depth pixels at the range within this share of the main blob's size around it are the leader too
    #: (landing gear, antennas: thin parts that depth edge holes cut off from the body).
    gather_fraction: float = 0.5
    #: Spinning propellers leave no depth: the box is widened by this share of the span on each side.
    side_pad_fraction: float = 0.15


@dataclass(frozen=True, slots=True)
class AutoLabel:
    """One frame's verdict; ``box_xyxy_px`` and ``quality`` only for a label."""

    verdict: Verdict
    reason: str
    box_xyxy_px: BoxT | None = None
    #: 0-1: how well the depth blob agrees with the projection in place and size.
    quality: float = 0.0
    #: The projection that was searched around (None behind the camera), px.
    expected_xyxy_px: BoxT | None = None
    expected_range_m: float = math.nan


def leader_in_camera(
    geometry: CameraGeometry, R_ned_body: Mat3, p_ned_follower_m: Vec3, p_ned_leader_m: Vec3
) -> Vec3:
    """The leader's centre in the camera frame, from both NED positions and the follower's attitude."""
    rel = np.asarray(p_ned_leader_m, np.float64) - np.asarray(p_ned_follower_m, np.float64)
    return geometry.ned_rel_to_cam(rel, R_ned_body)


def auto_label(
    depth_m: DepthImage, intrinsics: Intrinsics, p_cam_leader_m: Vec3, cfg: AutoLabelConfig
) -> AutoLabel:
    """The verdict for one frame (see the module docstring)."""
    x, y, z = (float(v) for v in p_cam_leader_m)
    w_px, h_px = intrinsics.width_px, intrinsics.height_px
    if z <= 0.0:
        return AutoLabel(Verdict.NEGATIVE, "leader behind the camera", expected_range_m=z)
    u = intrinsics.fx_px * x / z + intrinsics.cx_px
    v = intrinsics.fy_px * y / z + intrinsics.cy_px
    half_px = intrinsics.fx_px * cfg.leader_span_m / 2.0 / z
    expected = (u - half_px, v - half_px, u + half_px, v + half_px)
    reach_px = intrinsics.fx_px * 3.0 * cfg.position_sigma_m / z
    window = (expected[0] - reach_px, expected[1] - reach_px, expected[2] + reach_px, expected[3] + reach_px)
    if window[2] < 0 or window[3] < 0 or window[0] > w_px - 1 or window[1] > h_px - 1:
        return AutoLabel(Verdict.NEGATIVE, "leader outside the field of view", None, 0.0, expected, z)
    if not (0.0 <= u <= w_px - 1 and 0.0 <= v <= h_px - 1):
        return AutoLabel(Verdict.REJECTED, "leader at the image edge", None, 0.0, expected, z)
    if z < cfg.min_range_m or z > cfg.max_range_m:
        return AutoLabel(Verdict.REJECTED, "range outside the labelled span", None, 0.0, expected, z)

    x0, y0 = max(0, math.floor(window[0])), max(0, math.floor(window[1]))
    x1, y1 = min(w_px, math.ceil(window[2]) + 1), min(h_px, math.ceil(window[3]) + 1)
    patch = depth_m[y0:y1, x0:x1]
    tol_m = max(cfg.depth_tol_abs_m, cfg.depth_tol_rel * z) + cfg.leader_span_m
    mask = ((patch > 0.0) & (np.abs(patch - z) < tol_m)).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    min_area = max(6.0, cfg.min_blob_fraction * (2.0 * half_px) ** 2)
    blobs = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_area]
    if not blobs:
        return AutoLabel(Verdict.REJECTED, "no depth at the expected range", None, 0.0, expected, z)
    u_w, v_w = u - x0, v - y0
    best = min(blobs, key=lambda i: math.hypot(centroids[i][0] - u_w, centroids[i][1] - v_w))
    area = float(stats[best, cv2.CC_STAT_AREA])
    if any(i != best and stats[i, cv2.CC_STAT_AREA] >= cfg.rival_fraction * area for i in blobs):
        return AutoLabel(Verdict.REJECTED, "two objects at the expected range", None, 0.0, expected, z)
    bx, by, bw, bh = (int(stats[best, k]) for k in (0, 1, 2, 3))
    touches = (
        (bx == 0 and x0 > 0)
        or (by == 0 and y0 > 0)
        or (bx + bw == x1 - x0 and x1 < w_px)
        or (by + bh == y1 - y0 and y1 < h_px)
    )
    if touches:
        return AutoLabel(Verdict.REJECTED, "the blob runs into the background", None, 0.0, expected, z)
    grow = math.ceil(cfg.gather_fraction * max(bw, bh))
    gx0, gy0 = max(0, bx - grow), max(0, by - grow)
    gx1, gy1 = min(x1 - x0, bx + bw + grow), min(y1 - y0, by + bh + grow)
    ys, xs = np.nonzero(mask[gy0:gy1, gx0:gx1])
    pad_px = intrinsics.fx_px * cfg.side_pad_fraction * cfg.leader_span_m / z
    box = (
        max(0.0, x0 + gx0 + float(xs.min()) - pad_px),
        float(y0 + gy0 + ys.min()),
        min(float(w_px), x0 + gx0 + float(xs.max()) + 1.0 + pad_px),
        float(y0 + gy0 + ys.max() + 1),
    )
    size_ratio = max(box[2] - box[0], box[3] - box[1]) / (2.0 * half_px)
    if not (1.0 / cfg.max_size_ratio <= size_ratio <= cfg.max_size_ratio):
        return AutoLabel(Verdict.REJECTED, "blob size disagrees with the range", None, 0.0, expected, z)
    offset_px = math.hypot(centroids[best][0] - u_w, centroids[best][1] - v_w)
    sigma_px = max(1.0, reach_px / 3.0)
    quality = math.exp(-0.5 * (offset_px / sigma_px) ** 2) * min(size_ratio, 1.0 / size_ratio)
    if quality < cfg.min_quality:
        return AutoLabel(Verdict.REJECTED, "low quality", box, quality, expected, z)
    return AutoLabel(Verdict.LABEL, "", box, quality, expected, z)
