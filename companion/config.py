"""The service's configuration: frozen pydantic models loaded from TOML plus ``WINGMAN_*`` overrides.

Loaded once at the CLI edge and passed down explicitly; nothing below reads files or the environment.
Overrides use double underscores between levels and TOML literals as values, e.g.
``WINGMAN_LINK__URL=udpin://0.0.0.0:14541`` or ``WINGMAN_FORMATION__OFFSET_CAM_M='[0.0, 0.0, 6.0]'``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.kernel.camera import MountConfig
from companion.kernel.config import Section, deep_merge, env_overrides, format_validation_error, read_toml
from companion.kernel.errors import ConfigError

SCHEMA_VERSION = 1


class LinkConfig(Section):
    """The autopilot link (MAVSDK connection URL and timing)."""

    #: MAVSDK connection URL: ``udpin://HOST:PORT``, ``udpout://HOST:PORT``, ``tcpin://``/``tcpout://`` or
    #: ``serial:///dev/ttyX[:BAUD]``. PX4 SITL's vehicle i sends to 14540 + i: the simulator's follower
    #: (system 2) is 14541.
    url: str = "udpin://0.0.0.0:14541"
    #: MAVLink system id of the autopilot this service flies. 0: the first autopilot heard that is not the
    #: leader's (``leader.mavlink_system_id``). Any other autopilot on the link is never commanded.
    system_id: int = Field(2, ge=0, le=255)
    connect_timeout_s: float = Field(10.0, gt=0)
    #: MAVSDK resends setpoints at 20 Hz; PX4 needs > 2 Hz. This is how often *we* compute fresh ones.
    setpoint_rate_hz: float = Field(20.0, gt=2.0, le=100.0)
    command_timeout_s: float = Field(3.0, gt=0)
    #: No fresh setpoint from the mission for this long while streaming: the link stops offboard itself, so
    #: MAVSDK's 20 Hz resend can never keep a dead mission's last setpoint alive.
    setpoint_timeout_s: float = Field(0.5, gt=0)
    #: No telemetry for this long counts as a lost link.
    telemetry_timeout_s: float = Field(1.5, gt=0)
    #: What PX4 does when our setpoints stop for COM_OF_LOSS_T (a crashed service, a cut cable): the link
    #: sets COM_OBL_RC_ACT to it on connect (vehicle/failsafe.py). PX4's own default without RC is Return,
    #: which first climbs to RTL_RETURN_ALT (60 m) out of the formation; ``autopilot`` leaves PX4's setting.
    offboard_loss_action: Literal["hold", "land", "return", "autopilot"] = "hold"
    #: MAVSDK's own log lines go to the ``companion.vehicle.mavsdk`` logger at or above this level.
    mavsdk_log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "WARNING"

    @field_validator("url")
    @classmethod
    def _known_url(cls, v: str) -> str:
        problem = url_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v


class CameraConfig(Section):
    """Where RGB-D frames come from."""

    source: Literal["sim", "file", "realsense"] = "sim"
    #: file: a recorded folder or a RealSense .bag; sim: the simulator's camera socket.
    path: str = "/run/wingman/camera.sock"
    width_px: int = Field(640, gt=0)
    height_px: int = Field(480, gt=0)
    fps: float = Field(30.0, gt=0)
    realtime: bool = True
    loop: bool = False
    #: realsense: the D400 visual preset loaded at start (High Accuracy drops doubtful depth: fewer holes
    #: filled with wrong values at range, which is what the leader's pose needs).
    preset: Literal["default", "high_accuracy", "high_density", "medium_density"] = "high_accuracy"
    #: sim and file: how frame stamps reach the service clock. "mapped" (min-offset filter, see
    #: companion/service/stamps.py) when the source's clock is not the service's; "source" when it
    #: already is (``companion sim`` runs the service on the simulator's clock): the stamp is then the
    #: capture instant.
    stamps: Literal["mapped", "source"] = "mapped"
    mount: MountConfig = MountConfig()


class DetectorConfig(Section):
    """The leader detector."""

    model_path: str = "models/leader_detector.pt"
    #: Expected SHA-256 of the weights; empty to take it from the model card's sidecar file.
    model_sha256: str = ""
    #: ``truth``: the simulator's ground-truth boxes instead of the network (simulator and rendered
    #: recordings only), to exercise the service, pose and tracker without trained weights.
    runtime: Literal["auto", "torch", "onnx", "truth"] = "auto"
    input_size_px: int = Field(320, ge=128, le=1280, multiple_of=32)
    conf_threshold: float = Field(0.35, gt=0, lt=1)
    nms_iou: float = Field(0.5, gt=0, lt=1)
    threads: int = Field(2, ge=1, le=64)
    #: Search a magnified window on the tracked leader first (perception/detector/roi.py): a small leader
    #: scores far higher at 1.5x than at the whole frame's 0.5x, and the window costs less than the frame.
    roi_enabled: bool = True
    #: Window width in box widths (or the box height's equivalent at the frame's aspect ratio).
    roi_box_multiple: float = Field(3.0, ge=1.5, le=20.0)
    #: Network input px per window px (capped at ``input_size_px``).
    roi_magnification: float = Field(1.5, gt=0.1, le=4.0)
    roi_min_width_px: int = Field(128, ge=64, le=4096)
    #: A window wider than this fraction of the frame is not worth it: the whole frame is searched.
    roi_max_frame_fraction: float = Field(0.6, gt=0.0, le=1.0)
    #: Confidence threshold inside the window when no box passes ``conf_threshold`` (the best box only).
    #: Default: the same, no lowering. 0.2 raised closed-loop recall by 0.02-0.04, but in a leader-occluded
    #: run the window kept finding the tree behind the hidden leader, the tracker took it, the window
    #: followed it, and the follower flew past the leader at 1.23 m.
    roi_conf_threshold: float = Field(0.35, gt=0, lt=1)
    #: ...and only within this many missed frames of the last tracked box (longer: an occlusion).
    roi_low_conf_misses: int = Field(3, ge=0, le=100)
    #: Frames the window survives without a tracked box (missed detections, an occlusion), so a lost
    #: leader is looked for, magnified, where it was; the whole frame is still searched whenever the window
    #: finds nothing. 60 (4 s at 15 Hz, past leader-occluded's 3-s blind spell): seeds 1-8 7 completed + 1
    #: landed, min separation 2.44 m; 15 (the tracker's coast): 6 + 2 and 1.63 m (a phantom re-acquired
    #: from the whole frame); straight, circle, gps-loss, visibility (seeds 1-2) identical.
    roi_hold_frames: int = Field(60, ge=0, le=100)
    #: Network input (px) for the whole frame when there is no window on the leader (acquiring, lost) or the
    #: window found nothing: 640 searches a 640x480 frame at 1:1 instead of the 0.5x of ``input_size_px``.
    #: A quad 7 m away against the horizon was not found at 0.5x in 4 s of re-acquisition and was at 1:1
    #: (leader-occluded seed 9); the search costs ~4x the small input.
    search_input_px: int = Field(640, ge=128, le=1280, multiple_of=32)


class LeaderConfig(Section):
    """What the leader looks like, for the size prior and the surface-to-centre correction."""

    #: Motor-to-motor diagonal of the leader, m (a 450-class quad is 0.45).
    span_m: float = Field(0.45, gt=0.05, le=3.0)
    #: Half the body depth seen by the camera: depth measured on the front surface + this = centre.
    surface_to_centre_m: float = Field(0.05, ge=0.0, le=1.0)
    #: How far the middle of the leader's silhouette sits below its centre (landing legs hang below,
    #: propellers sit above), m: the box centre is shifted up by this before it is used.
    box_centre_below_m: float = Field(0.04, ge=-0.5, le=0.5)
    #: Where the leader's own position comes from when it is shared (vision-external-position fallback).
    shared_position: Literal["none", "mavlink", "mqtt"] = "none"
    mavlink_system_id: int = Field(1, ge=1, le=255)


class PoseConfig(Section):
    """Leader position from a box and the aligned depth: depth window, stereo noise model, box jitter."""

    #: Depth outside [depth_min_m, depth_max_m] is treated as invalid (D435: ~0.2 m minimum range).
    #: Keep depth_max_m at or below the camera's own cut-off: the pose undoes the bias of a known cut.
    depth_min_m: float = Field(0.2, ge=0.0)
    depth_max_m: float = Field(10.0, gt=0.0)
    #: Stereo depth noise sigma_z = z^2 * subpixel / (f * baseline) per pixel (D435: 50 mm, ~0.08 px).
    stereo_baseline_m: float = Field(0.05, gt=0.0)
    stereo_subpixel_px: float = Field(0.08, gt=0.0)
    #: At most this many box pixels count as independent depth samples (stereo noise is correlated).
    independent_depth_px: int = Field(16, ge=1)
    #: Extra depth uncertainty from the leader's shape (where the visible surface is vs its centre), m.
    surface_model_std_m: float = Field(0.02, ge=0.0)
    #: Box-centre jitter of the detector: this many pixels plus this fraction of the box size.
    box_jitter_px: float = Field(1.0, ge=0.0)
    box_jitter_frac: float = Field(0.03, ge=0.0)
    #: Fewer valid depth pixels than this inside a box: no depth measurement.
    min_valid_px: int = Field(6, ge=1)
    #: Without depth (beyond the stereo range, a hole), range the leader from its box size, learnt
    #: online from depth measurements at closer range.
    size_fallback: bool = True
    #: The size is learnt from depth measurements from this fraction of ``depth_max_m`` out to 0.95 of it.
    #: The network's box height barely changes with range (0.333 / 0.330 / 0.329 m apparent at 3-7.5 /
    #: 7.5-10 / 10-12 m on the weave) but swings 5-10 % with the leader's tilt and yaw, so the mean over
    #: the wider band is the better size: 0.75 (the last 2 s before the cut-off) gave the 6-12 m
    #: band 0.266 m on the weave and 0.389 m on a fresh render of it, 0.5 gives 0.157 / 0.221 (the arc,
    #: inside 10 m for only 2 s before going out, is unchanged). Exact renderer boxes grow at close range
    #: and do better at 0.75: check a retrained detector (docs/perception.md).
    size_learn_min_frac: float = Field(0.5, ge=0.0, lt=0.95)
    #: ...but not nearer than this fraction of ``depth_max_m``: a leader that near returns stereo depth
    #: (the D435i noise model's holes are single pixels), so a box with none there is something beyond
    #: the cut-off seen past the leader (the tree behind it), not the leader. Judged by the track's
    #: predicted range when there is a track, else by the box's own size range. 0 turns it off.
    #: leader-occluded, seeds 1-8: seed 7 had tracked the tree and landed; with 0.8 it completes (5 -> 6
    #: of 8 completed); straight, circle, gps-loss and visibility (seeds 1-2) identical either way.
    #: A real camera with wide holes on a dark airframe at 5-8 m would lose those frames (not ranged).
    size_fallback_min_frac: float = Field(0.8, ge=0.0, lt=1.0)
    #: A box this many times the size a leader would have at its depth cluster's range has ranged
    #: something behind the leader (a thin quad in front of a tree fills a small share of its box): the
    #: box is searched again for a sparser cluster in front, where its size puts the leader, and takes
    #: it when there is one. A correct box is 1.1-1.5x (a loose one up to ~2x: it keeps its cluster).
    #: leader-occluded seed 7 re-acquired a leader 4.4 m away at the tree's 7.2 m (size ratio 2.0-2.5),
    #: flew at it and came within 0.57 m (measured in lockstep). 0 turns it off.
    size_suspect_ratio: float = Field(1.8, ge=0.0)


class TrackerConfig(Section):
    """Constant-velocity Kalman tracker of the leader's position relative to the follower."""

    process_accel_std_m_s2: float = Field(2.0, gt=0)
    gate_chi2: float = Field(16.27, gt=0)  # chi-square 3 dof, p = 0.001
    confirm_hits: int = Field(3, ge=1)
    confirm_window: int = Field(5, ge=1)
    coast_timeout_s: float = Field(1.5, gt=0)
    lost_timeout_s: float = Field(3.0, gt=0)
    #: Frames over which a track's recent hit ratio is counted (15: 1 s at 15 Hz); the mission reads it
    #: before it takes a new track after a loss as the leader (``mission.reacquire_min_hit_ratio``).
    quality_window_frames: int = Field(15, ge=1, le=300)
    size_ratio_tolerance: float = Field(2.5, gt=1.0)
    #: A second object seen steadily outside the track's gate (in at least ``switch_hits`` of the last
    #: ``quality_window_frames`` frames) replaces a track seen in at most ``switch_max_track_ratio`` of
    #: them: a false track confirmed on a distant tree before the leader came into view otherwise kept
    #: gating the leader out. 0 hits = never.
    switch_hits: int = Field(12, ge=0)
    switch_max_track_ratio: float = Field(0.3, ge=0.0, le=1.0)
    #: ... or sooner, once seen in ``switch_fast_hits`` frames, when its hit ratio over its frames beats the
    #: track's by ``switch_ratio_margin``: the leader reappearing beside a tree crossed the view in 9 frames
    #: while a false track on the crown, hit in a third of its frames, held the follower's eye
    #: (leader-occluded seed 8). A steady leader track (0.8-1.0) cannot be beaten by 0.5. 0 = off.
    switch_fast_hits: int = Field(6, ge=0)
    switch_ratio_margin: float = Field(0.5, gt=0.0, le=1.0)
    #: While a new track is tentative, what is seen outside its gate in as many frames with a higher mean
    #: detector score takes it over (still tentative): a false box seen first, on the frame the leader was
    #: missed, otherwise confirmed and held the track for 0.2 s of the leader in plain view.
    contend_tentative: bool = True
    #: Velocity uncertainty of a new track (the leader's relative speed is unknown at first sight), m/s.
    init_velocity_std_m_s: float = Field(3.0, gt=0)
    #: Acceleration noise along the line of sight while the track is ranged by box size (beyond the
    #: stereo range), m/s^2: size ranges are 10-25 % per frame, and only a smoother radial motion model
    #: averages enough of them (6-12 m band on the rendered sequences, RMS over 4 box-noise seeds:
    #: 0.24-0.35 m at 1.0, 0.23-0.47 m at 2.0; 0.5 lags a leader turning back).
    size_range_accel_std_m_s2: float = Field(1.0, gt=0)
    #: A constant-acceleration (Singer) filter beside the track, fed the measurements the track accepts,
    #: estimates the leader's acceleration for the formation law's lead (instead of the law
    #: differentiating the leader's velocity). The track, its gate and its estimate stay constant-velocity.
    leader_accel_filter: bool = False
    #: That filter's white-noise jerk, m/s^3; the time constant its acceleration decays with between
    #: measurements, s; a new track's acceleration uncertainty, m/s^2.
    jerk_std_m_s3: float = Field(3.0, gt=0)
    accel_tau_s: float = Field(2.0, gt=0)
    init_accel_std_m_s2: float = Field(1.0, gt=0)


class FormationConfig(Section):
    """The formation law: desired slot and PID gains on the offset error."""

    #: Desired leader position in the camera frame at level flight (x right, y down, z forward), m.
    offset_cam_m: tuple[float, float, float] = (0.0, 0.0, 5.0)
    #: Tuned on the circle (15 m, 3 m/s) against the simulator's PX4-like velocity loop, whose tracking
    #: error varies once per revolution: kp 0.9 / ki 0.05 left 0.27 m RMSE, these 0.13 m.
    kp_xy: float = 1.8
    ki_xy: float = 0.1
    kd_xy: float = 0.8
    i_limit_xy_m_s: float = 0.5
    kp_z: float = 0.8
    ki_z: float = 0.1
    i_limit_z_m_s: float = 0.4
    #: Feed-forward of the leader's estimated velocity (0 = the paper's pure PID, 1 = full).
    leader_velocity_ff: float = Field(1.0, ge=0.0, le=1.0)
    #: Feed-forward of the leader's estimated acceleration as a velocity lead, s. PX4's velocity loop
    #: follows a setpoint with a lag of about 1 / MPC_XY_VEL_P_ACC (0.55 s); without this lead the follower
    #: trails an accelerating leader by accel x lag / kp_xy (0.7 m at 1.5 m/s^2). 0 turns it off.
    leader_accel_ff_s: float = Field(0.7, ge=0.0, le=2.0)
    #: The same lead on the vertical, s. 0: none. PX4's vertical velocity loop is about twice as fast as the
    #: horizontal (MPC_Z_VEL_P_ACC 4 against MPC_XY_VEL_P_ACC 1.8), and the vertical acceleration estimate
    #: is the noisiest (elevation and the follower's pitch): under link-loss's late attitudes it swung the
    #: height 0.3-0.6 m (lockstep, seeds 1-4).
    leader_accel_ff_z_s: float = Field(0.0, ge=0.0, le=2.0)
    #: Low-pass time constant of that acceleration estimate (the derivative of the leader's velocity), s.
    #: 0.2 with ff 0.7 (was 0.3 / 0.6) and the lead dropped while coasting: straight lockstep seeds 1-8
    #: mean max deviation 0.338 -> 0.295 m (lockstep).
    leader_accel_tau_s: float = Field(0.2, gt=0.0, le=5.0)
    #: Keep the acceleration lead while the track coasts (no detection). False drops it then: a coasting
    #: estimate's velocity is extrapolated, and the faster lead amplified it (circle seed 3 with tau 0.2 and
    #: the lead kept: 1.34 m, the follower past the leader at 1.51 m).
    accel_lead_while_coasting: bool = False
    kp_yaw: float = 1.5
    max_yaw_rate_deg_s: float = Field(60.0, gt=0)
    max_accel_m_s2: float = Field(3.0, gt=0)
    #: How fast the velocity command may change, m/s^2 (a first command that jumped to the full PID output
    #: pitched the vehicle past 40 deg). Faster cuts the leader-start lag but, for every track, lost the
    #: leader in leader-occluded (8.0: 8 of 8 seeds landed with an earlier detector), so only a steady
    #: track gets the faster ``command_slew_steady_m_s2``; this one also bounds the vertical.
    command_slew_m_s2: float = Field(3.0, gt=0)
    #: The slew while the track is steady: confirmed and seen in at least ``steady_hit_ratio`` of its
    #: recent frames (``tracker.quality_window_frames``), and the link on time (``steady_link_age_s``),
    #: m/s^2; horizontal only (the vertical keeps ``command_slew_m_s2``). 8.0 against 3.0 (lockstep, mean
    #: max deviation, seeds 1-4, lockstep): straight 0.416 -> 0.350 m, circle,
    #: gps-loss, figure8 and wind 14-24 % lower. It was off (3.0) while it cost leader-occluded seeds, until
    #: the detector learnt trees and the whole-frame search went to 1:1 (``search_input_px``).
    command_slew_steady_m_s2: float = Field(8.0, gt=0)
    #: The attitude's age averaged over ~1 s above this (s) marks the link late: the fast slew waits
    #: ``steady_link_hold_s``. Under link-loss's 30 % loss and 40 ms latency the fast slew swung the height
    #: 0.4-0.6 m (3.0: 0.25-0.3); the average there is ~0.033 s, on a clean link ~0.005 s.
    steady_link_age_s: float = Field(0.02, gt=0)
    steady_link_hold_s: float = Field(3.0, ge=0)
    steady_hit_ratio: float = Field(0.8, ge=0.0, le=1.0)


class MissionConfig(Section):
    """The mission state machine's policy."""

    takeoff_altitude_m: float = Field(5.0, gt=1.0)
    gps_loss_policy: Literal["vision_attitude", "vision_external_position", "land"] = "vision_attitude"
    leader_lost_action: Literal["hold", "land", "rtl"] = "land"
    reacquire_coast_s: float = Field(2.0, ge=0)
    reacquire_scan_s: float = Field(10.0, ge=0)
    #: A new track found after the leader was lost is taken as the leader only once it is this old (s)
    #: and was seen in at least this share of its recent frames (``tracker.quality_window_frames``).
    #: Why: while the leader was hidden, sporadic false detections of a tree behind it (2-5 of every 8
    #: frames) made a confirmed track 3.5 m beyond the leader; the follower re-acquired it, flew through
    #: the reappearing leader at 0.78 m and chased the phantom to the geofence (leader-occluded seed 7,
    #: ``command_slew_m_s2`` 8). The real leader, seen again, is detected in 0.8-1.0 of frames.
    reacquire_min_track_s: float = Field(0.8, ge=0.0)
    reacquire_min_hit_ratio: float = Field(0.6, ge=0.0, le=1.0)
    scan_yaw_rate_deg_s: float = Field(30.0, gt=0)
    #: An estimate older than this (since its frame's capture) is stale: HOVER, never resent. Younger
    #: ones are flown brought to the control instant with the follower's own motion (mission/ego.py),
    #: so a late frame on a loaded companion computer (0.3-0.8 s measured) is not a stop.
    stale_estimate_s: float = Field(1.0, gt=0)
    #: Hover this long on a stalled perception pipeline before the abort action.
    stall_hover_s: float = Field(3.0, ge=0)
    acquire_timeout_s: float = Field(60.0, gt=0)
    landing_speed_m_s: float = Field(0.6, gt=0, le=0.7)
    shutdown_action: Literal["hold_then_land", "land", "hold"] = "hold_then_land"
    #: hold_then_land: how long PX4 holds before it is told to land. Without GPS every action is PX4 Land.
    shutdown_hold_s: float = Field(10.0, ge=0)
    #: GPS counts as lost after this long without a 3D fix (PX4 drops the fix ~1 s after the last sample).
    gps_loss_confirm_s: float = Field(0.5, ge=0)
    #: ... and as back after this long with a 3D fix and a valid estimate.
    gps_restore_s: float = Field(5.0, ge=0)
    takeoff_timeout_s: float = Field(40.0, gt=0)
    #: vision_external_position: how long PX4 may take to accept the external fix before we stay on attitude.
    external_position_accept_s: float = Field(5.0, gt=0)
    #: Hover thrust to start the attitude law from when PX4's MPC_THR_HOVER cannot be read (0..1).
    hover_thrust_norm: float = Field(0.5, gt=0.05, lt=0.95)
    #: A service (re)started while its vehicle is already armed and flying only observes and reports until
    #: ``companion start``. True: it takes the vehicle back into offboard by itself (after a crash under
    #: ``Restart=on-failure``, too) as soon as it has a GPS verdict. Risk: a restarted service flies
    #: whatever slot and leader it now sees, with nobody having confirmed that it should.
    resume_in_air: bool = False


class SafetyConfig(Section):
    """Hard limits that every setpoint passes through."""

    max_speed_m_s: float = Field(5.0, gt=0)
    max_vertical_speed_m_s: float = Field(1.5, gt=0)
    max_tilt_deg: float = Field(25.0, gt=0, lt=60)
    min_altitude_m: float = Field(2.0, ge=0)
    max_altitude_m: float = Field(40.0, gt=0)
    min_separation_m: float = Field(2.0, gt=0)
    #: Seconds of the present closing speed the separation barrier sets aside before braking. PX4's velocity
    #: loop (MPC_XY_VEL_P_ACC 1.8/s) sheds speed slowly as it nears the setpoint, and a leader that turns
    #: across the line of sight adds closing of its own: 0.5 s let a follower come within 1.87 m of a leader
    #: cornering at 2 m/s (leader-occluded, lockstep, network); 1.0 s kept 2.37 m, formation unchanged.
    separation_response_s: float = Field(1.0, ge=0.0, le=5.0)
    geofence_radius_m: float = Field(200.0, gt=0)
    #: The depth guard (companion/perception/obstacle.py): the separation barrier also holds against the
    #: nearest thing in the depth image's central window that is not the tracked leader, taken as static.
    depth_guard: bool = True
    #: Only what is nearer than this counts, m; the window's width and height as image fractions; how
    #: many sampled depth pixels (every 4th) an object needs.
    depth_guard_range_m: float = Field(4.0, gt=0.5, le=20.0)
    #: Flying toward what the camera sees, the guard looks out to the follower's stopping distance
    #: (``min_separation_m``, plus ``separation_response_s`` of the speed, plus braking at the barrier's
    #: deceleration) when that is beyond ``depth_guard_range_m``, up to this, m: at 3.6 m/s 4 m is 1.1 s,
    #: under the 9.9 m the barrier needs to hold ``min_separation_m`` off a pole.
    depth_guard_max_range_m: float = Field(9.0, gt=0.5, le=20.0)
    depth_guard_window_frac: tuple[float, float] = (0.6, 0.3)
    depth_guard_min_px: int = Field(8, ge=1)
    #: What comes within this of the path the follower will fly (formation.path_approach) is passed with
    #: this much room at least, m: the follower steps aside from it, or brakes when it is dead ahead
    #: (``depth_guard_hit_radius_m``). 0.8 and 0.6 gave the same visibility runs (lockstep, seeds 1-8),
    #: but at 0.6 leader-occluded (seeds 1-16) passed trees at 0.60 m and 11 completed against 13.
    depth_guard_corridor_m: float = Field(0.8, gt=0)
    #: Within this of the path the follower would hit it (half a 450-class quad's span with propellers,
    #: 0.33 m): it brakes, holding ``min_separation_m`` as from the leader. Between this and the corridor it
    #: slides past, its velocity turned away from the obstacle's side, at full speed: braking for a pole
    #: 0.6 m beside the path left the follower 1.1-1.8 m behind its slot (visibility, lockstep).
    depth_guard_hit_radius_m: float = Field(0.35, gt=0)

    @model_validator(mode="after")
    def _guard_ranges(self) -> SafetyConfig:
        if self.depth_guard_max_range_m < self.depth_guard_range_m:
            raise ValueError("depth_guard_max_range_m must be >= depth_guard_range_m")
        return self


class MqttConfig(Section):
    """Telemetry to an MQTT broker (topics under ``<topic_prefix>/<vehicle_id>/``)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(1883, ge=1, le=65535)
    topic_prefix: str = Field("wingman", pattern=r"^[A-Za-z0-9_/-]{1,64}$")
    username: str = ""
    #: A file holding the password (never the password itself in the config).
    password_file: str = ""
    tls: bool = False
    #: CA bundle for the broker's certificate; empty: the system's CAs.
    ca_file: str = ""
    #: Client certificate and key for mutual TLS; both or neither.
    cert_file: str = ""
    key_file: str = ""
    keepalive_s: int = Field(10, ge=2, le=600)
    #: Reconnect backoff: jittered, doubling from min to max.
    reconnect_min_s: float = Field(0.5, gt=0)
    reconnect_max_s: float = Field(30.0, gt=0)
    state_rate_hz: float = Field(2.0, gt=0)
    pose_rate_hz: float = Field(10.0, gt=0)
    health_rate_hz: float = Field(0.5, gt=0)
    #: state and events messages kept while disconnected; the oldest are dropped (and counted) beyond it.
    buffer_messages: int = Field(1000, ge=1)
    #: Accept land/hold/set_offset on <prefix>/<vehicle_id>/cmd, each signed with command_key_file.
    command_topic: bool = False
    command_key_file: str = ""
    command_max_age_s: float = Field(30.0, gt=0)
    #: Where the leader's shared position arrives when leader.shared_position = "mqtt".
    leader_topic: str = "wingman/leader/position"

    @model_validator(mode="after")
    def _consistent(self) -> MqttConfig:
        if self.command_topic and not self.command_key_file:
            raise ValueError("command_topic = true needs command_key_file (commands must be authenticated)")
        if bool(self.cert_file) != bool(self.key_file):
            raise ValueError("cert_file and key_file go together")
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError("reconnect_min_s must be <= reconnect_max_s")
        if any(c in self.leader_topic for c in "#+"):
            raise ValueError("leader_topic must not contain wildcards")
        return self


class StatusConfig(Section):
    """The local status endpoint (a Unix socket, mode 0660)."""

    socket_path: str = "/run/wingman/status.sock"


class ServiceConfig(Section):
    """Lifecycle of the service and what it tells the ground station over MAVLink."""

    #: Start the mission (arm, take off, follow) as soon as preflight passes, without `companion start`.
    #: For the simulator and test stands; on a drone an operator starts it.
    auto_start: bool = False
    #: Bound on the safe action at SIGTERM/SIGINT (hold, land, disarm) before exiting anyway.
    #: Keep the unit's TimeoutStopSec above this.
    shutdown_timeout_s: float = Field(120.0, gt=0)
    #: STATUSTEXT to the ground station on every mission state change.
    statustext: bool = True
    #: ONBOARD_COMPUTER_STATUS (CPU, memory, temperatures) to the ground station; 0 turns it off.
    onboard_status_rate_hz: float = Field(1.0, ge=0, le=10)
    #: How often the machine's load and temperatures are sampled.
    system_sample_period_s: float = Field(1.0, gt=0)


class LoggingConfig(Section):
    """Log format and level; set once at the CLI edge."""

    format: Literal["human", "json"] = "human"
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"


class AutoLabelSection(Section):
    """Recording the leader's box from its shared position while GPS is good (a dataset to fine-tune on)."""

    #: Off by default: recording writes images to disk for as long as the formation flies.
    enabled: bool = False
    #: Dataset folder; each service start writes a new sub-folder named by its start time.
    out_dir: str = "/var/lib/wingman/autolabel"
    #: Stop writing beyond this many bytes per start (images and labels).
    max_bytes: int = Field(2_000_000_000, gt=0)
    #: A shared leader position older than this at a frame's time is not used, s.
    share_max_age_s: float = Field(0.5, gt=0.0, le=5.0)
    #: 1-sigma error of the expected leader position (both GPS fixes and the share's age), m.
    position_sigma_m: float = Field(0.5, gt=0.0, le=5.0)
    #: Spinning propellers leave no depth: the box is widened by this share of the span on each side.
    side_pad_fraction: float = Field(0.15, ge=0.0, le=1.0)
    #: Keep one drone-free frame in this many as a negative.
    negative_every: int = Field(5, ge=1)


class Config(Section):
    """The whole service configuration."""

    schema_version: int = SCHEMA_VERSION
    vehicle_id: str = Field("follower1", pattern=r"^[A-Za-z0-9_-]{1,32}$")
    link: LinkConfig = LinkConfig()
    camera: CameraConfig = CameraConfig()
    detector: DetectorConfig = DetectorConfig()
    leader: LeaderConfig = LeaderConfig()
    pose: PoseConfig = PoseConfig()
    tracker: TrackerConfig = TrackerConfig()
    formation: FormationConfig = FormationConfig()
    mission: MissionConfig = MissionConfig()
    safety: SafetyConfig = SafetyConfig()
    mqtt: MqttConfig = MqttConfig()
    status: StatusConfig = StatusConfig()
    service: ServiceConfig = ServiceConfig()
    logging: LoggingConfig = LoggingConfig()
    autolabel: AutoLabelSection = AutoLabelSection()

    @model_validator(mode="after")
    def _truth_needs_truth(self) -> Config:
        if self.detector.runtime == "truth" and self.camera.source == "realsense":
            raise ValueError("detector.runtime = 'truth' needs a source with ground truth (sim or file)")
        return self

    @model_validator(mode="after")
    def _never_the_leader(self) -> Config:
        if self.link.system_id != 0 and self.link.system_id == self.leader.mavlink_system_id:
            raise ValueError(
                f"link.system_id: {self.link.system_id} is the leader's (leader.mavlink_system_id); "
                "the service never commands the leader"
            )
        return self

    @field_validator("schema_version")
    @classmethod
    def _known_schema(cls, v: int) -> int:
        if v > SCHEMA_VERSION:
            raise ValueError(f"written for a newer Wingman (schema {v} > {SCHEMA_VERSION}); upgrade")
        if v < 1:
            raise ValueError("must be >= 1")
        return v


_URL_SCHEMES = ("udpin", "udpout", "tcpin", "tcpout", "serial")


def url_problem(url: str) -> str | None:
    """What is wrong with a MAVSDK connection URL, in words; None when it is well formed."""
    scheme, sep, rest = url.partition("://")
    if not sep or scheme not in _URL_SCHEMES:
        return f"expected one of {', '.join(s + '://' for s in _URL_SCHEMES)}..."
    if scheme == "serial":
        device, _, baud = rest.partition(":")
        if not device.startswith("/dev/"):
            return "serial:// needs a device path, e.g. serial:///dev/ttyTHS1:921600"
        if baud and not baud.isdigit():
            return f"serial baud rate must be a number (got {baud!r})"
        return None
    host, colon, port = rest.rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        return f"{scheme}:// needs HOST:PORT with a port in 1-65535 (got {rest!r})"
    return None


def load_config(path: Path | None, environ: Mapping[str, str] | None = None) -> Config:
    """Load the service config from ``path`` (defaults when None) with environment overrides on top."""
    data = read_toml(path) if path is not None else {}
    data = deep_merge(data, env_overrides(os.environ if environ is None else environ))
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path or "<defaults>"), format_validation_error(exc)) from None
