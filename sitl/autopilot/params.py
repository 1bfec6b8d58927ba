"""PX4 parameters the simulated autopilot honours, with PX4's names, types and defaults (pure).

Values are kept as Python floats (INT32 values are integral floats). On the wire PX4 encodes INT32
parameters *bytewise* in PARAM_VALUE's float field (AUTOPILOT_VERSION advertises
PARAM_ENCODE_BYTEWISE), which is what MAVSDK's parameter client and QGroundControl expect;
:func:`encode_value` and :func:`decode_value` do that.

One deliberate difference: PX4 stores any value a client sets and constrains it where it is used; we
clamp to the documented range when it is set and echo the clamped value back, so that an absurd
PARAM_SET cannot push the controllers into nonsense.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Final

# MAV_PARAM_TYPE values used by PX4.
PARAM_TYPE_INT32: Final = 6
PARAM_TYPE_REAL32: Final = 9


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One parameter: PX4 name, MAV_PARAM_TYPE, default and the range we accept."""

    name: str
    type: int
    default: float
    min: float = -math.inf
    max: float = math.inf


def _f(name: str, default: float, lo: float = -math.inf, hi: float = math.inf) -> ParamSpec:
    return ParamSpec(name, PARAM_TYPE_REAL32, default, lo, hi)


def _i(name: str, default: int, lo: float = -(2.0**31), hi: float = 2.0**31 - 1) -> ParamSpec:
    return ParamSpec(name, PARAM_TYPE_INT32, float(default), lo, hi)


#: PX4 v1.15 defaults (``*_params.c`` / ``module.yaml``), SITL overrides where PX4 SITL has them.
PARAM_SPECS: Final[tuple[ParamSpec, ...]] = (
    # Multicopter position control limits and gains (mc_pos_control).
    _f("MPC_XY_VEL_MAX", 12.0, 0.0, 20.0),
    _f("MPC_XY_CRUISE", 5.0, 0.0, 20.0),
    _f("MPC_Z_VEL_MAX_UP", 3.0, 0.5, 8.0),
    _f("MPC_Z_VEL_MAX_DN", 1.5, 0.5, 4.0),
    _f("MPC_Z_V_AUTO_UP", 3.0, 0.5, 8.0),
    _f("MPC_Z_V_AUTO_DN", 1.5, 0.5, 4.0),
    _f("MPC_TILTMAX_AIR", 45.0, 20.0, 89.0),
    _f("MPC_TKO_SPEED", 1.5, 0.1, 5.0),
    _f("MPC_LAND_SPEED", 0.7, 0.2, 3.0),
    _f("MPC_LAND_ALT1", 10.0, 0.0, 122.0),
    _f("MPC_LAND_ALT2", 5.0, 0.0, 122.0),
    _f("MPC_THR_HOVER", 0.5, 0.1, 0.8),
    _f("MPC_THR_MIN", 0.12, 0.05, 0.5),
    _f("MPC_THR_MAX", 1.0, 0.0, 1.0),
    _f("MPC_ACC_HOR", 3.0, 2.0, 15.0),
    _f("MPC_ACC_HOR_MAX", 5.0, 2.0, 15.0),
    _f("MPC_ACC_UP_MAX", 4.0, 2.0, 15.0),
    _f("MPC_ACC_DOWN_MAX", 3.0, 2.0, 15.0),
    _f("MPC_XY_P", 0.95, 0.0, 2.0),
    _f("MPC_Z_P", 1.0, 0.0, 2.0),
    _f("MPC_XY_VEL_P_ACC", 1.8, 1.2, 5.0),
    _f("MPC_XY_VEL_I_ACC", 0.4, 0.0, 60.0),
    _f("MPC_XY_VEL_D_ACC", 0.2, 0.1, 2.0),
    _f("MPC_Z_VEL_P_ACC", 4.0, 2.0, 15.0),
    _f("MPC_Z_VEL_I_ACC", 2.0, 0.2, 3.0),
    _f("MPC_Z_VEL_D_ACC", 0.0, 0.0, 2.0),
    _f("MPC_YAWRAUTO_MAX", 45.0, 0.0, 360.0),
    # Attitude and rate control (mc_att_control, mc_rate_control).
    _f("MC_ROLL_P", 6.5, 0.0, 12.0),
    _f("MC_PITCH_P", 6.5, 0.0, 12.0),
    _f("MC_YAW_P", 2.8, 0.0, 5.0),
    _f("MC_YAW_WEIGHT", 0.4, 0.0, 1.0),
    _f("MC_ROLLRATE_MAX", 220.0, 0.0, 1800.0),
    _f("MC_PITCHRATE_MAX", 220.0, 0.0, 1800.0),
    _f("MC_YAWRATE_MAX", 200.0, 0.0, 1800.0),
    # Navigator: takeoff, RTL.
    _f("MIS_TAKEOFF_ALT", 2.5, 0.0, 500.0),
    _f("NAV_MC_ALT_RAD", 0.8, 0.05, 200.0),
    _f("NAV_ACC_RAD", 10.0, 0.05, 200.0),
    _f("RTL_RETURN_ALT", 60.0, 0.0, 1000.0),
    _f("RTL_DESCEND_ALT", 30.0, 2.0, 500.0),
    _f("RTL_LAND_DELAY", 0.0, -1.0, 300.0),
    # Commander: offboard, failsafes, arming, disarming.
    _f("COM_OF_LOSS_T", 1.0, 0.0, 60.0),
    _i("COM_OBL_RC_ACT", 0, 0, 7),
    _i("NAV_RCL_ACT", 2, 0, 6),
    _i("NAV_DLL_ACT", 0, 0, 6),
    _i("COM_RC_IN_MODE", 1, 0, 4),
    _f("COM_DISARM_LAND", 2.0, -1.0, 20.0),
    _f("COM_DISARM_PRFLT", 10.0, -1.0, 20.0),
    _f("COM_POS_FS_EPH", 5.0, 0.0, 1000.0),
    _f("COM_VEL_FS_EVH", 1.0, 0.0, 100.0),
    _i("COM_TAKEOFF_ACT", 0, 0, 1),
    _f("COM_FAIL_ACT_T", 5.0, 0.0, 25.0),
    _i("COM_ARM_WO_GPS", 1, 0, 2),
    _i("SYS_FAILURE_EN", 1, 0, 1),
    # Estimator (ekf2).
    _i("EKF2_NOAID_TOUT", 5_000_000, 500_000, 10_000_000),
    _i("EKF2_EV_CTRL", 0, 0, 15),  # PX4's default: no external-vision aiding until asked
    _i("EKF2_GPS_CTRL", 7, 0, 15),
    _i("EKF2_HGT_REF", 1, 0, 3),
    _f("EKF2_REQ_EPH", 3.0, 2.0, 100.0),
    # Identity and misc (QGroundControl reads these).
    _i("MAV_SYS_ID", 1, 1, 250),
    _i("MAV_COMP_ID", 1, 1, 250),
    _i("MAV_TYPE", 2, 0, 22),
    _i("SYS_AUTOSTART", 4001, 0, 9_999_999),
    _i("BAT1_N_CELLS", 4, 1, 16),
    _i("SYS_HITL", 0, -1, 2),
    _i("CBRK_USB_CHK", 197848, 0, 197848),
)

SPECS_BY_NAME: Final[dict[str, ParamSpec]] = {s.name: s for s in PARAM_SPECS}


def encode_value(value: float, param_type: int) -> float:
    """The float that goes into PARAM_VALUE.param_value (INT32 bytes reinterpreted, as PX4 does)."""
    if param_type == PARAM_TYPE_INT32:
        packed = struct.pack("<i", int(value))
        encoded: float = struct.unpack("<f", packed)[0]
        return encoded
    return float(value)


def decode_value(raw: float, param_type: int) -> float | None:
    """The value a PARAM_SET carries, or None if it is unusable (NaN/inf, unknown type)."""
    if param_type in (1, 2, 3, 4, 5, 6):  # UINT8..INT32: PX4 reads them bytewise as an int32
        try:
            as_int: int = struct.unpack("<i", struct.pack("<f", raw))[0]
        except (OverflowError, struct.error):
            return None
        return float(as_int)
    if param_type == PARAM_TYPE_REAL32:
        return raw if math.isfinite(raw) else None
    return None


class ParamStore:
    """The autopilot's parameters: a sorted table (PX4 indexes parameters by name order).

    ``version`` increases on every change so controllers can refresh cached values cheaply.
    """

    def __init__(self, overrides: dict[str, float] | None = None) -> None:
        self.names: tuple[str, ...] = tuple(sorted(SPECS_BY_NAME))
        self._index = {n: i for i, n in enumerate(self.names)}
        self.values: dict[str, float] = {s.name: s.default for s in PARAM_SPECS}
        self.version = 0
        for name, value in (overrides or {}).items():
            if name not in SPECS_BY_NAME:
                raise KeyError(f"unknown parameter {name!r}")
            self.set(name, value)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def index_of(self, name: str) -> int | None:
        return self._index.get(name)

    def spec(self, name: str) -> ParamSpec | None:
        return SPECS_BY_NAME.get(name)

    def set(self, name: str, value: float) -> float:
        """Set ``name`` (clamped to its range, integral for INT32); returns the value stored."""
        spec = SPECS_BY_NAME[name]
        if not math.isfinite(value):
            return self.values[name]
        stored = min(spec.max, max(spec.min, value))
        if spec.type == PARAM_TYPE_INT32:
            stored = float(round(stored))
        if stored != self.values[name]:
            self.values[name] = stored
            self.version += 1
        return stored
