"""What the follower sees and how it estimates its leader: camera, detector, leader, pose, tracker."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.kernel.camera import MountConfig
from companion.kernel.config import Section


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
    input_size_px: int = Field(416, ge=128, le=1280, multiple_of=32)
    conf_threshold: float = Field(0.35, gt=0, lt=1)
    nms_iou: float = Field(0.5, gt=0, lt=1)
    threads: int = Field(2, ge=1, le=64)
    #: Search a magnified window on the tracked leader first (perception/detector/roi.py): a small leader
    #: scores far higher at 1.75x than at the whole frame's 0.65x, and the window costs less than the frame.
    roi_enabled: bool = True
    #: Window width in box widths (or the box height's equivalent at the frame's aspect ratio).
    roi_box_multiple: float = Field(3.0, ge=1.5, le=20.0)
    #: Network input px per window px (capped at ``input_size_px``).
    roi_magnification: float = Field(1.75, gt=0.1, le=4.0)
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
    #: Without a window (acquiring, or the window dropped), every other whole-frame search runs at
    #: ``input_size_px`` instead: a leader close by (on the ground 5 m ahead before take-off) can score
    #: under the threshold at 1:1 when the network was trained for a smaller input, while a distant one
    #: needs the 1:1. Alternating costs nothing per frame. A window's fallback search stays at 1:1.
    search_alternate: bool = True


class LeaderConfig(Section):
    """What the leader looks like, for the size prior and the surface-to-centre correction."""

    #: Motor-to-motor diagonal of the leader, m (a 450-class quad is 0.45).
    span_m: float = Field(0.45, gt=0.05, le=3.0)
    #: Half the body depth seen by the camera: depth measured on the front surface + this = centre.
    surface_to_centre_m: float = Field(0.05, ge=0.0, le=1.0)
    #: How far the middle of the leader's silhouette sits below its centre (landing legs hang below,
    #: propellers sit above), m: the box centre is shifted up by this before it is used.
    box_centre_below_m: float = Field(0.04, ge=-0.5, le=0.5)
    #: Where the leader's own position comes from when it is shared (vision-external-position fallback,
    #: formations): "mqtt" subscribes to ``mqtt.leader_topic``.
    shared_position: Literal["none", "mqtt"] = "none"
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
    #: The same in height (down), m/s^2; None takes ``process_accel_std_m_s2``. Smaller steadies the
    #: follower's height (0.7: vertical speed in formation 0.09 -> 0.03 m/s RMS, no height swing after a
    #: bad depth) but lags a climbing leader; docs/flight.md has what it did to the starts.
    process_accel_std_z_m_s2: float | None = Field(None, gt=0)
    gate_chi2: float = Field(16.27, gt=0)  # chi-square 3 dof, p = 0.001
    #: A box's height is taken with less weight the further it is off the track's (a Student-t of this
    #: many degrees of freedom on the height innovation, beyond one sigma; 0: the plain Kalman update).
    #: One box off in height (d^2 14, inside the gate) kicked the track's vertical rate to 1 m/s, the
    #: next eight boxes fell outside the gate and the follower dove 0.9 m (circle seed 6, lockstep with
    #: the real path's timing); 1 takes that out, but is left off: in a formation flight the outer
    #: follower drew a long loss of the leader with it (docs/flight.md).
    height_outlier_dof: float = Field(0.0, ge=0.0)
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
    #: A track that never had stereo depth and stays over ``far_field_margin_m`` beyond the slot's range
    #: is dropped once the follower has flown ``far_field_flown_m`` toward it and its range fell by less
    #: than ``far_field_closure`` of that: something at infinity (a gap between clouds) keeps its bearing
    #: and its box size however the follower flies, and a follower chasing one climbed 32 m in 30 s.
    #: Boxes without depth within ``far_field_cone_deg`` of its bearing are then ignored for
    #: ``far_field_ignore_s``. 0 m flown = off.
    far_field_flown_m: float = Field(6.0, ge=0.0)
    far_field_closure: float = Field(0.25, ge=0.0, lt=1.0)
    far_field_margin_m: float = Field(1.0, ge=0.0)
    far_field_cone_deg: float = Field(5.0, gt=0.0, lt=90.0)
    far_field_ignore_s: float = Field(120.0, ge=0.0)
