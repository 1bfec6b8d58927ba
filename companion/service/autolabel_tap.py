"""Auto-labelling in flight: the service's frames, its telemetry and the leader's shared position.

While the follower's GPS is good and a shared leader position is fresh, every frame goes through
:func:`companion.perception.autolabel.auto_label` and on to a background
:class:`~companion.perception.autolabel_writer.AutoLabelWriter`; the flight loop never waits for the disk.
The lockstep harness labels through :func:`label_frame` too, so the simulator checks what the service does.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.config import Config
from companion.kernel.camera import RgbdFrame
from companion.kernel.flight import VehicleState
from companion.mission.types import SharedLeaderPosition
from companion.perception.autolabel import AutoLabel, AutoLabelConfig, auto_label, leader_in_camera
from companion.perception.autolabel_writer import AutoLabelCounts, AutoLabelWriter
from companion.perception.transform import AttitudeHistory, CameraGeometry


def label_frame(
    frame: RgbdFrame,
    vehicle: VehicleState,
    attitude: AttitudeHistory,
    p_ned_leader_m: NDArray[np.float64] | None,
    *,
    geometry: CameraGeometry,
    cfg: AutoLabelConfig,
) -> AutoLabel | None:
    """The frame's verdict, or None when it cannot be labelled (GPS not good, no attitude or no share)."""
    R_ned_body = attitude.R_at(frame.stamp_s)
    if not vehicle.global_position_ok or R_ned_body is None or p_ned_leader_m is None:
        return None
    # Position telemetry is newer than the frame: step it back along the velocity.
    back_s = vehicle.local_position_stamp_s - frame.stamp_s
    p_follower = np.asarray(vehicle.p_ned_m, np.float64) - back_s * np.asarray(vehicle.v_ned_m_s)
    p_cam = leader_in_camera(geometry, R_ned_body, p_follower, p_ned_leader_m)
    return auto_label(frame.depth_m, frame.intrinsics, p_cam, cfg)


class SharedLeaderTrack:
    """The leader's shared positions, as they arrive, moved to a frame's time.

    A share carries no velocity: the last two give it. Older than ``max_age_s`` at the frame: no position.
    """

    def __init__(self, max_age_s: float) -> None:
        self.max_age_s = max_age_s
        self._last: SharedLeaderPosition | None = None
        self._prev: SharedLeaderPosition | None = None

    def add(self, position: SharedLeaderPosition) -> None:
        """A shared leader position (stamped on the frames' clock); one older than the last is ignored."""
        if self._last is None or position.stamp_s > self._last.stamp_s:
            self._prev, self._last = self._last, position

    def at(self, stamp_s: float) -> NDArray[np.float64] | None:
        """The leader's position at ``stamp_s``: the last share moved along the last two shares' velocity."""
        last = self._last
        if last is None or abs(stamp_s - last.stamp_s) > self.max_age_s:
            return None
        p = np.asarray(last.p_ned_m, np.float64)
        prev = self._prev
        if prev is not None and 0.0 < last.stamp_s - prev.stamp_s <= 1.0:
            v = (p - np.asarray(prev.p_ned_m, np.float64)) / (last.stamp_s - prev.stamp_s)
            p = p + (stamp_s - last.stamp_s) * v
        return p


class AutoLabelTap:
    """The service's auto-labeller: shares in, frames in, a dataset out (``[autolabel]`` in the config)."""

    def __init__(self, cfg: Config, geometry: CameraGeometry, now_wall_s: float | None = None) -> None:
        a = cfg.autolabel
        self.leader = SharedLeaderTrack(a.share_max_age_s)
        self.cfg = AutoLabelConfig(
            leader_span_m=cfg.leader.span_m,
            position_sigma_m=a.position_sigma_m,
            side_pad_fraction=a.side_pad_fraction,
            depth_tol_abs_m=0.6,
        )
        self.geometry = geometry
        started = time.strftime("%Y%m%d-%H%M%S", time.gmtime(now_wall_s))
        self.writer = AutoLabelWriter(
            Path(a.out_dir) / started,
            sequence=started,
            max_bytes=a.max_bytes,
            negative_every=a.negative_every,
        )
        self.gated_out = 0

    def __enter__(self) -> AutoLabelTap:
        self.writer.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.__exit__(*exc)

    @property
    def counts(self) -> AutoLabelCounts:
        return self.writer.counts

    def share(self, position: SharedLeaderPosition) -> None:
        """A shared leader position (its stamp on the frames' clock)."""
        self.leader.add(position)

    def on_frame(self, frame: RgbdFrame, vehicle: VehicleState, attitude: AttitudeHistory) -> None:
        label = label_frame(
            frame, vehicle, attitude, self.leader.at(frame.stamp_s), geometry=self.geometry, cfg=self.cfg
        )
        if label is None:
            self.gated_out += 1
            return
        self.writer.offer(frame, label)
