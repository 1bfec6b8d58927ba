"""PX4's MAVLink telemetry: stream tables and the message builders (``src/modules/mavlink/streams``).

Every builder reads the autopilot's *estimate* (and the attitude PX4 would report), never the true
position: a vehicle without GPS reports exactly the drifting, invalid-flagged estimate PX4 would.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Final

from pymavlink.dialects.v20 import common as mavlink

if TYPE_CHECKING:
    from sitl.autopilot.state import AutopilotState

MAV_TYPE_QUADROTOR: Final = 2
MAV_AUTOPILOT_PX4: Final = 12

# MAV_SYS_STATUS_SENSOR bits (SYS_STATUS).
SENSOR_GYRO: Final = 1
SENSOR_ACCEL: Final = 2
SENSOR_MAG: Final = 4
SENSOR_ABS_PRESSURE: Final = 8
SENSOR_GPS: Final = 32
SENSOR_VISION_POSITION: Final = 128
SENSOR_ATTITUDE_STABILIZATION: Final = 2048
SENSOR_YAW_POSITION: Final = 4096
SENSOR_Z_ALTITUDE_CONTROL: Final = 8192
SENSOR_XY_POSITION_CONTROL: Final = 16384
SENSOR_MOTOR_OUTPUTS: Final = 32768
SENSOR_AHRS: Final = 1 << 21
SENSOR_LOGGING: Final = 1 << 24
SENSOR_BATTERY: Final = 1 << 25
SENSOR_PREARM_CHECK: Final = 1 << 28

# ESTIMATOR_STATUS flags.
EST_ATTITUDE, EST_VELOCITY_HORIZ, EST_VELOCITY_VERT, EST_POS_HORIZ_REL = 1, 2, 4, 8
EST_POS_HORIZ_ABS, EST_POS_VERT_ABS, EST_POS_VERT_AGL, EST_CONST_POS_MODE = 16, 32, 64, 128
EST_PRED_POS_HORIZ_REL, EST_PRED_POS_HORIZ_ABS, EST_GPS_GLITCH = 256, 512, 1024

# AUTOPILOT_VERSION capabilities PX4 advertises (mavlink_main.cpp).
CAPABILITIES: Final = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_FTP
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)
#: PX4 v1.15.0 release, packed as PX4 does (major << 24 | minor << 16 | patch << 8 | type 255=release).
FLIGHT_SW_VERSION: Final = (1 << 24) | (15 << 16) | (0 << 8) | 255

#: The special interval meaning "send on every update" (PX4's unlimited-rate streams).
ON_UPDATE: Final = 0.0

#: Default stream rates in Hz for PX4's "onboard" mode (the API link, 14540+i), mavlink_main.cpp.
ONBOARD_RATES_HZ: Final[dict[int, float]] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 100.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: math.inf,  # on every GPS update
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 10.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 10.0,
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_TIMESYNC: 10.0,
}

#: PX4's "normal" mode (the GCS link, 18570+i -> 14550): what QGroundControl gets.
NORMAL_RATES_HZ: Final[dict[int, float]] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 15.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 10.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 1.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 0.5,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
}


def _clip_i(x: float, lo: int, hi: int) -> int:
    """A float field as a MAVLink integer: truncated like PX4's casts, clamped to the type's range."""
    if x >= hi:
        return hi
    if x <= lo:
        return lo
    if x != x:  # NaN  # noqa: PLR0124 - the cheapest NaN test, and this runs for every field
        return 0
    return int(x)


def heartbeat(ap: AutopilotState) -> mavlink.MAVLink_message:
    """HEARTBEAT: quad, PX4 autopilot, base_mode/custom_mode of the current nav state."""
    nav = ap.nav_state
    return mavlink.MAVLink_heartbeat_message(
        MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, nav.base_mode(ap.armed), nav.custom_mode, ap.system_status(), 3
    )


def sys_status(ap: AutopilotState) -> mavlink.MAVLink_message:
    """SYS_STATUS: sensor present/enabled/health bits (GPS only while GNSS is fused), battery."""
    present, enabled, health = ap.sensor_bits()
    return mavlink.MAVLink_sys_status_message(
        present, enabled, health, 250, ap.battery.voltage_mv, ap.battery.current_ca, ap.battery.remaining_pct,
        0, 0, 0, 0, 0, 0, 0, 0, 0,
    )  # fmt: skip


def system_time(ap: AutopilotState) -> mavlink.MAVLink_message:
    """SYSTEM_TIME: unix time and time since boot, both following sim time."""
    return mavlink.MAVLink_system_time_message(ap.unix_time_us(), ap.time_boot_ms())


def attitude(ap: AutopilotState) -> mavlink.MAVLink_message:
    """ATTITUDE: Euler angles and body rates."""
    d = ap.dyn
    return mavlink.MAVLink_attitude_message(
        ap.time_boot_ms(), d.roll_rad, d.pitch_rad, ap.yaw_est_rad(), d.p_rad_s, d.q_rad_s, d.r_rad_s
    )


def attitude_quaternion(ap: AutopilotState) -> mavlink.MAVLink_message:
    """ATTITUDE_QUATERNION: body -> NED quaternion and body rates."""
    d = ap.dyn
    w, x, y, z = ap.attitude_q()
    return mavlink.MAVLink_attitude_quaternion_message(
        ap.time_boot_ms(), w, x, y, z, d.p_rad_s, d.q_rad_s, d.r_rad_s, (0.0, 0.0, 0.0, 0.0)
    )


def local_position_ned(ap: AutopilotState) -> mavlink.MAVLink_message:
    """LOCAL_POSITION_NED: the estimate (drifting after GPS loss; no validity flags)."""
    e = ap.est
    return mavlink.MAVLink_local_position_ned_message(
        ap.time_boot_ms(), e.n_m, e.e_m, e.d_m, e.vn_m_s, e.ve_m_s, e.vd_m_s
    )


def global_position_int(ap: AutopilotState) -> mavlink.MAVLink_message | None:
    """GLOBAL_POSITION_INT: the estimate as lat/lon/alt (None before the EKF has an origin)."""
    g = ap.global_estimate()
    if g is None:
        return None  # PX4 publishes no global position before the EKF has an origin
    home_alt = ap.home.alt_m if ap.home is not None else ap.origin.alt0_m
    vn, ve, vd = g.v_ned_m_s
    return mavlink.MAVLink_global_position_int_message(
        ap.time_boot_ms(),
        _clip_i(g.lat_deg * 1e7, -900_000_000, 900_000_000),
        _clip_i(g.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
        _clip_i(g.alt_amsl_m * 1000.0, -(2**31), 2**31 - 1),
        _clip_i((g.alt_amsl_m - home_alt) * 1000.0, -(2**31), 2**31 - 1),
        _clip_i(vn * 100.0, -32768, 32767),
        _clip_i(ve * 100.0, -32768, 32767),
        _clip_i(vd * 100.0, -32768, 32767),
        _clip_i(g.yaw_deg * 100.0, 0, 35999),
    )


def gps_raw_int(ap: AutopilotState) -> mavlink.MAVLink_message:
    """GPS_RAW_INT: the last receiver fix, or "no GPS" (fix 0, 65535s) after 1 s without data."""
    g = ap.gps_last
    t_us = int(ap.t_s * 1e6)
    if g is None or ap.t_s - g.t_s > 1.0:
        # No receiver data for > 1 s: PX4 keeps the stream alive at 1 Hz with "no GPS".
        return mavlink.MAVLink_gps_raw_int_message(
            t_us, 0, 0, 0, 0, 65535, 65535, 65535, 65535, 255, 0, 0, 0, 0, 0, 0
        )  # fmt: skip
    speed = math.hypot(g.vn_m_s, g.ve_m_s)
    cog = math.degrees(math.atan2(g.ve_m_s, g.vn_m_s)) % 360.0 if speed > 0.2 else 0.0
    return mavlink.MAVLink_gps_raw_int_message(
        int(g.t_s * 1e6),
        g.fix_type,
        _clip_i(g.lat_deg * 1e7, -900_000_000, 900_000_000),
        _clip_i(g.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
        _clip_i(g.alt_m * 1000.0, -(2**31), 2**31 - 1),
        _clip_i(g.eph_m * 100.0, 0, 65535),
        _clip_i(g.epv_m * 100.0, 0, 65535),
        _clip_i(speed * 100.0, 0, 65535),
        _clip_i(cog * 100.0, 0, 35999),
        g.satellites,
        _clip_i(g.alt_m * 1000.0, -(2**31), 2**31 - 1),
        _clip_i(g.eph_m * 1000.0, 0, 2**32 - 1),
        _clip_i(g.epv_m * 1000.0, 0, 2**32 - 1),
        _clip_i(ap.gps.noise.vel_white_m_s * 1000.0, 0, 2**32 - 1),
        0,
        0,
    )


def extended_sys_state(ap: AutopilotState) -> mavlink.MAVLink_message:
    """EXTENDED_SYS_STATE: landed state."""
    return mavlink.MAVLink_extended_sys_state_message(0, ap.landed_state())


def estimator_status(ap: AutopilotState) -> mavlink.MAVLink_message:
    """ESTIMATOR_STATUS: EKF2 solution flags and accuracies."""
    e = ap.est
    return mavlink.MAVLink_estimator_status_message(
        int(ap.t_s * 1e6), ap.estimator_flags(), 0.1, 0.1 if e.xy_valid else 1.0, 0.1, 0.05, 0.0, 0.0,
        e.eph_m, e.epv_m,
    )  # fmt: skip


def odometry(ap: AutopilotState) -> mavlink.MAVLink_message:
    """ODOMETRY: local NED pose, body-frame velocity (as PX4 sends it), covariances from eph/epv."""
    e = ap.est
    d = ap.dyn
    q = ap.attitude_q()
    # PX4 sends velocity in the child frame (body FRD).
    w, x, y, z = q
    vn, ve, vd = e.vn_m_s, e.ve_m_s, e.vd_m_s
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    bvx = r00 * vn + r10 * ve + r20 * vd
    bvy = r01 * vn + r11 * ve + r21 * vd
    bvz = r02 * vn + r12 * ve + r22 * vd
    var_p = e.eph_m * e.eph_m
    pose_cov = [math.nan] * 21
    pose_cov[0] = pose_cov[6] = var_p
    pose_cov[11] = e.epv_m * e.epv_m
    vel_cov = [math.nan] * 21
    vel_cov[0] = vel_cov[6] = e.evh_m_s * e.evh_m_s
    vel_cov[11] = e.evv_m_s * e.evv_m_s
    return mavlink.MAVLink_odometry_message(
        int(ap.t_s * 1e6), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD,
        e.n_m, e.e_m, e.d_m, list(q), bvx, bvy, bvz, d.p_rad_s, d.q_rad_s, d.r_rad_s,
        pose_cov, vel_cov, e.reset_counter, mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, 0,
    )  # fmt: skip


def highres_imu(ap: AutopilotState) -> mavlink.MAVLink_message:
    """HIGHRES_IMU: specific force, gyro, a synthetic magnetometer and baro."""
    d = ap.dyn
    fx, fy, fz = d.specific_force_body()
    yaw = d.yaw_rad  # the magnetometer senses the true heading
    # A level-ish magnetometer reading pointing at magnetic north (Zurich: ~0.21 G horizontal, 0.43 G down).
    mx, my = 0.21 * math.cos(-yaw), 0.21 * math.sin(-yaw)
    alt = ap.origin.alt0_m - ap.est.d_m
    pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * alt) ** 5.25588 if alt < 40000 else 0.0
    return mavlink.MAVLink_highres_imu_message(
        int(ap.t_s * 1e6), fx, fy, fz, d.p_rad_s, d.q_rad_s, d.r_rad_s, mx, my, 0.43,
        pressure_hpa, 0.0, alt, 20.0, 0x1FFF, 0,
    )  # fmt: skip


def altitude(ap: AutopilotState) -> mavlink.MAVLink_message:
    """ALTITUDE: AMSL, local and relative-to-home altitude of the estimate."""
    e = ap.est
    amsl = ap.origin.alt0_m - e.d_m
    home_d = ap.home.d_m if ap.home is not None else 0.0
    return mavlink.MAVLink_altitude_message(
        int(ap.t_s * 1e6), amsl, amsl, -e.d_m, home_d - e.d_m, math.nan, math.nan
    )


def vfr_hud(ap: AutopilotState) -> mavlink.MAVLink_message:
    """VFR_HUD: ground speed, heading, throttle, altitude and climb rate."""
    e = ap.est
    gs = math.hypot(e.vn_m_s, e.ve_m_s)
    hdg = int(math.degrees(ap.yaw_est_rad()) % 360.0)
    return mavlink.MAVLink_vfr_hud_message(
        gs, gs, hdg, _clip_i(ap.thrust_sp * 100.0, 0, 100), ap.origin.alt0_m - e.d_m, -e.vd_m_s
    )


def battery_status(ap: AutopilotState) -> mavlink.MAVLink_message:
    """BATTERY_STATUS: the simple 4S battery model."""
    b = ap.battery
    cells = [b.voltage_mv // 4] * 4 + [65535] * 6
    return mavlink.MAVLink_battery_status_message(
        0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 2500, cells, b.current_ca,
        int(b.consumed_mah), -1, b.remaining_pct, 0, mavlink.MAV_BATTERY_CHARGE_STATE_OK, [0, 0, 0, 0], 0, 0,
    )  # fmt: skip


def timesync(ap: AutopilotState) -> mavlink.MAVLink_message:
    """TIMESYNC request (tc1 = 0, ts1 = now in ns)."""
    return mavlink.MAVLink_timesync_message(0, int(ap.t_s * 1e9))


def home_position(ap: AutopilotState) -> mavlink.MAVLink_message | None:
    """HOME_POSITION (None until home is set)."""
    h = ap.home
    if h is None:
        return None
    return mavlink.MAVLink_home_position_message(
        _clip_i(h.lat_deg * 1e7, -900_000_000, 900_000_000),
        _clip_i(h.lon_deg * 1e7, -1_800_000_000, 1_800_000_000),
        _clip_i(h.alt_m * 1000.0, -(2**31), 2**31 - 1),
        h.n_m, h.e_m, h.d_m, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(ap.t_s * 1e6),
    )  # fmt: skip


def autopilot_version(ap: AutopilotState) -> mavlink.MAVLink_message:
    """AUTOPILOT_VERSION: PX4 v1.15 capabilities (MAVSDK reads MISSION_INT from them)."""
    return mavlink.MAVLink_autopilot_version_message(
        CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x26AC, 0x0011,
        0x5753_0000 + ap.sysid, [0] * 18,
    )  # fmt: skip


Builder = Callable[["AutopilotState"], "mavlink.MAVLink_message | None"]

BUILDERS: Final[dict[int, Builder]] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: heartbeat,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: sys_status,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: system_time,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: attitude,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: attitude_quaternion,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: local_position_ned,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: global_position_int,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: gps_raw_int,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: extended_sys_state,
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: estimator_status,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: odometry,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: highres_imu,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: altitude,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: vfr_hud,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: battery_status,
    mavlink.MAVLINK_MSG_ID_TIMESYNC: timesync,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: home_position,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: autopilot_version,
}
