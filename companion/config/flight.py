"""How the follower flies: the formation law, the mission's policies and the safety limits."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from companion.kernel.config import Section


class FormationConfig(Section):
    """The formation law: desired slot and PID gains on the offset error."""

    #: Desired leader position in the camera frame at level flight (x right, y down, z forward), m.
    offset_cam_m: tuple[float, float, float] = (0.0, 0.0, 5.0)
    #: Tuned on the circle (15 m, 3 m/s) against the simulator's PX4-like velocity loop, whose tracking
    #: error varies once per revolution: kp 0.9 / ki 0.05 left 0.27 m RMSE, these 0.13 m. A young or
    #: blinking track is flown on this; a steady one on ``kp_xy_steady``.
    kp_xy: float = 1.8
    #: The range gain while the track is steady (the same test as ``command_slew_steady_m_s2``), 1/s:
    #: trails an accelerating leader less. 2.5 for every track re-acquired a leader beyond a tree in
    #: leader-occluded and flew into the tree on the way back (docs/evaluation.md), hence only here.
    kp_xy_steady: float = Field(2.5, gt=0.0, le=5.0)
    #: The range gain of the GPS-lost attitude law, 1/s: its outer loop feeds its own relative-velocity
    #: loop (``FormationLaw.KV_XY_1_S``), not PX4's, and is kept apart from ``kp_xy`` so that each is
    #: tuned for its loop.
    kp_xy_attitude: float = Field(1.8, gt=0.0, le=5.0)
    ki_xy: float = 0.1
    #: On the range rate (the tracker's relative velocity), s. 1.2 with ``kp_xy_steady`` 2.5 damps the
    #: catch-up after the leader's start (0.8 overshot as far as it had trailed; 1.6 trailed more).
    kd_xy: float = 1.2
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
    #: The horizontal lead fades below about this acceleration, m/s^2 (scaled by |a|^2 / (|a|^2 + fade^2)):
    #: the estimate's noise while the leader hovers otherwise swings the follower. 0: the full lead always.
    leader_accel_fade_m_s2: float = Field(0.0, ge=0.0, le=5.0)
    #: The lead's part along the line of sight fades out over this much range error, m, while it would push
    #: a range error that is already growing further (the follower closing in past its slot while the
    #: leader's speed-up is still being led): the acceleration estimate trails the leader's, so the lead
    #: outlives a speed-up by a few tenths of a second and overshot half the turn-ins of `circle`. 0: the full
    #: lead always. Opt-in (0.07 measured): with it a follower in `leader-occluded` re-acquired a cloud and
    #: chased it (docs/flight.md).
    leader_accel_yield_m: float = Field(0.0, ge=0.0, le=5.0)
    #: ...beyond this much range error, m (the hover's noise leaves the lead alone).
    leader_accel_yield_dead_m: float = Field(0.03, ge=0.0, le=5.0)
    #: Keep the acceleration lead while the track coasts (no detection). False drops it then: a coasting
    #: estimate's velocity is extrapolated, and the faster lead amplified it (circle seed 3 with tau 0.2 and
    #: the lead kept: 1.34 m, the follower past the leader at 1.51 m).
    accel_lead_while_coasting: bool = False
    #: A leader that shares its autopilot's velocity (``leader.shared_position = "mqtt"``) is led on that
    #: velocity and its acceleration (the change between consecutive shares, low-passed per share over
    #: ``shared_accel_tau_s``, the velocity carried forward over the share's age), not on the camera's,
    #: while a share younger than ``shared_motion_max_age_s`` carries one: the camera's positions
    #: differentiated twice read a leader's start 0.3-0.5 s late. REACQUIRE coasts on it too. False: the
    #: camera's estimate alone (a formation plan still takes the shared velocity).
    lead_on_shared_motion: bool = True
    shared_accel_tau_s: float = Field(0.1, gt=0.0, le=2.0)
    shared_motion_max_age_s: float = Field(0.4, gt=0.0, le=2.0)
    #: While the camera misses a leader led on its shares (above) for longer than a frame or two, FOLLOW
    #: flies on the camera's last relative position carried on at the shares' relative velocity, and
    #: after 2 s on where the shares put the leader, moved by their mean offset from the camera's
    #: position over ``shared_offset_tau_s`` while the camera saw it (both ends' GPS errors;
    #: docs/flight.md). The track's constant-velocity coast drifts off a turning leader by decimetres a
    #: second. False: the coast alone.
    coast_on_shared_position: bool = True
    shared_offset_tau_s: float = Field(2.0, gt=0.0, le=30.0)
    #: Bring each leader estimate from its frame's capture instant to the control tick, with the
    #: follower's own motion in between (companion/mission/ego.py). False flies on the estimate as
    #: captured (the paper's way): for comparison campaigns only.
    latency_compensation: bool = True
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
    #: 0.6, not 0.8: at 0.8 four missed frames of a long-held track just as the leader started held the
    #: fast slew back for its first 0.35 s. A young track still needs ``confirm_hits`` first, and the tracker
    #: keeps a far pair of size-ranged boxes from pulling it onto the camera (docs/perception.md).
    steady_hit_ratio: float = Field(0.6, ge=0.0, le=1.0)
    #: A formation plan (``config/formations/*.toml``; a relative path as companion/config/paths.py says:
    #: the config file's folder, then the shipped files). Empty: a lone follower on ``offset_cam_m``. With a
    #: plan the service flies the slot named by ``vehicle_id``: ``offset_cam_m`` and ``slot_leader_m`` are
    #: set from it at load time.
    plan: str = ""
    #: The follower's place in the leader's level heading frame (forward, right, down), m. With the leader's
    #: shared heading the follower holds this place as the leader turns; without it (or None) only the range
    #: and the bearing of ``offset_cam_m`` are held and the follower trails where it is.
    slot_leader_m: tuple[float, float, float] | None = None
    #: The other followers' slots in the same plan (forward, right, down), m: where neighbours should be,
    #: which tells the leader from a look-alike neighbour after GPS loss. Set from ``plan``.
    neighbour_slots_m: tuple[tuple[float, float, float], ...] = ()
    #: The other followers' vehicle ids in the plan: their MQTT ``pose`` topics are read for separation
    #: and for the leader's identity. Set from ``plan``.
    neighbour_ids: tuple[str, ...] = ()
    #: How fast an error across the line of sight to the slot is corrected, 1/s (the range has ``kp_xy``).
    kp_slot_1_s: float = Field(1.5, ge=0.0, le=5.0)
    #: A lone follower (no ``slot_leader_m``) moves around the leader to trail it: the angle between the line
    #: of sight and the leader's course is flown out at this rate, 1/s (0: the follower keeps its place in
    #: NED and the leader's turns bring it beside or in front of the follower, whose camera then looks at a
    #: leader flown at backwards; on PX4 SIH's drag that tilt put the leader out of the image).
    trail_gain_1_s: float = Field(0.8, ge=0.0, le=5.0)
    #: Send the velocity in NED with an acceleration feed-forward (the leader's acceleration and the thrust
    #: the learnt drag takes at the commanded velocity) and an absolute yaw, as PX4's offboard setpoints
    #: accept; false: a body-frame velocity and yaw rate, no feed-forward (docs/flight.md).
    acceleration_feedforward: bool = False
    #: ...at most this fast across the line of sight, m/s, and in full only once the leader is faster than
    #: ``trail_min_speed_m_s`` + 0.5 m/s (faded in from ``trail_min_speed_m_s``: a hovering leader has no
    #: course).
    trail_max_m_s: float = Field(1.5, ge=0.0, le=10.0)
    trail_min_speed_m_s: float = Field(0.5, ge=0.0)
    #: ...and only past this angle between the line of sight and the leader's course, deg: within it the
    #: follower keeps its place in NED (45: the leader is never flown at backwards and keeps at least a
    #: third of its speed forward in the follower's frame, nose down, where the camera looks up at it).
    trail_free_deg: float = Field(45.0, ge=0.0, le=180.0)
    #: The slot's own acceleration (as it turns with the leader) fed forward as a velocity lead, s; the
    #: same reason as ``leader_accel_ff_s``. 0 turns it off.
    slot_accel_ff_s: float = Field(0.35, ge=0.0, le=2.0)
    #: The join (companion/mission/join.py): entering the formation this far (m) or more from the slot, the
    #: follower flies a planned approach at up to ``join_speed_m_s`` relative to the leader, accelerating
    #: and braking at ``join_accel_m_s2``, instead of the full gain on the whole error. 0 m/s: no join.
    join_speed_m_s: float = Field(1.5, ge=0.0, le=10.0)
    join_accel_m_s2: float = Field(1.0, gt=0.0, le=5.0)
    join_min_error_m: float = Field(0.5, ge=0.0)


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
    #: An obstacle counts once this many frames in a row see it (one within ``min_separation_m`` at once):
    #: one frame's depth 2 m short where the leader is read as an obstacle 3 m ahead.
    depth_guard_confirm_frames: int = Field(2, ge=1, le=10)
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
