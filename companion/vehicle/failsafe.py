"""PX4's offboard-loss failsafe: which ``COM_OBL_RC_ACT`` the link asks for, and how to say what PX4 will do.

Why: when our setpoints stop for COM_OF_LOSS_T (a crashed service, a cut serial cable), PX4 runs
COM_OBL_RC_ACT. Its default (0, Position) needs a pilot's sticks, so without RC PX4 falls to NAV_RCL_ACT,
default 2, Return: it first climbs to RTL_RETURN_ALT (60 m by default) from the middle of a formation and
then flies home. In link-loss's 1.5 s total cut the follower was climbing at 1.8 m/s when the link came
back, and peaked 1.2 m above the leader. A follower that simply stops (Hold) is what a pilot standing
beside the formation expects; Hold needs a position estimate, so without GPS PX4 falls through Return and
Land to Descend by itself.
"""

from __future__ import annotations

from typing import Final, Literal

OffboardLossAction = Literal["hold", "land", "return", "autopilot"]

PARAM: Final = "COM_OBL_RC_ACT"
#: COM_OBL_RC_ACT values (PX4 commander): 3 Return, 4 Land, 5 Hold.
VALUE: Final[dict[str, int]] = {"return": 3, "land": 4, "hold": 5}
_NAMES: Final[dict[int, str]] = {
    0: "Position (without RC: NAV_RCL_ACT, default Return)",
    1: "Altitude (without RC: NAV_RCL_ACT, default Return)",
    2: "Stabilized (without RC: NAV_RCL_ACT, default Return)",
    3: "Return",
    4: "Land",
    5: "Hold",
    6: "Terminate",
    7: "Disarm",
}


def wanted_value(action: OffboardLossAction) -> int | None:
    """The COM_OBL_RC_ACT to set for ``action``; None for ``autopilot`` (leave PX4's own)."""
    return VALUE.get(action)


def describe(value: int) -> str:
    """What PX4 does on offboard loss for a COM_OBL_RC_ACT ``value``, in words."""
    return _NAMES.get(value, f"unknown ({value})")


def not_applied(action: OffboardLossAction, reason: str) -> str:
    """The one warning line for a COM_OBL_RC_ACT that could not be set (or read)."""
    what = "readable" if action == "autopilot" else f"set to {action}"
    return f"PX4 offboard-loss failsafe not {what} ({PARAM}: {reason}); PX4 keeps its own (default: Return)"


def applied(action: OffboardLossAction, value: int) -> tuple[bool, str]:
    """Whether PX4's ``value`` is what ``action`` asked for, and the line that says what PX4 will do."""
    wanted = wanted_value(action)
    ok = wanted is None or value == wanted
    return ok, f"PX4 offboard-loss failsafe: {describe(value)} ({PARAM} {value})"
