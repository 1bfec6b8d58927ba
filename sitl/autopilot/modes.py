"""PX4 navigation states, their HEARTBEAT encoding and their names.

Sources: ``px4_custom_mode.h``, ``commander/ModeUtil``, ``lib/modes/ui.hpp``.
"""

from __future__ import annotations

from enum import Enum
from typing import Final

# HEARTBEAT base_mode flags (MAV_MODE_FLAG).
MODE_FLAG_CUSTOM_MODE_ENABLED: Final = 1
MODE_FLAG_AUTO_ENABLED: Final = 4
MODE_FLAG_GUIDED_ENABLED: Final = 8
MODE_FLAG_STABILIZE_ENABLED: Final = 16
MODE_FLAG_MANUAL_INPUT_ENABLED: Final = 64
MODE_FLAG_SAFETY_ARMED: Final = 128

# PX4 main modes and AUTO sub-modes.
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = (
    1,
    2,
    3,
    4,
    5,
    6,
    7,
)
SUB_AUTO_TAKEOFF, SUB_AUTO_LOITER, SUB_AUTO_MISSION, SUB_AUTO_RTL, SUB_AUTO_LAND = 2, 3, 4, 5, 6


class NavState(Enum):
    """What the vehicle is doing. ``value`` is (main mode, sub mode, UI name)."""

    MANUAL = (MAIN_MANUAL, 0, "Manual")
    ALTCTL = (MAIN_ALTCTL, 0, "Altitude")
    POSCTL = (MAIN_POSCTL, 0, "Position")
    STAB = (MAIN_STABILIZED, 0, "Stabilized")
    ACRO = (MAIN_ACRO, 0, "Acro")
    AUTO_MISSION = (MAIN_AUTO, SUB_AUTO_MISSION, "Mission")
    AUTO_LOITER = (MAIN_AUTO, SUB_AUTO_LOITER, "Hold")
    AUTO_RTL = (MAIN_AUTO, SUB_AUTO_RTL, "Return")
    AUTO_TAKEOFF = (MAIN_AUTO, SUB_AUTO_TAKEOFF, "Takeoff")
    AUTO_LAND = (MAIN_AUTO, SUB_AUTO_LAND, "Land")
    OFFBOARD = (MAIN_OFFBOARD, 0, "Offboard")
    #: The Descend failsafe: PX4 reports it on MAVLink as AUTO.LAND.
    DESCEND = (MAIN_AUTO, SUB_AUTO_LAND, "Descend")
    TERMINATION = (MAIN_MANUAL, 0, "Termination")

    @property
    def ui_name(self) -> str:
        name: str = self.value[2]
        return name

    @property
    def custom_mode(self) -> int:
        """PX4's ``custom_mode``: ``main << 16 | sub << 24``."""
        main, sub, _ = self.value
        return (main << 16) | (sub << 24)

    @property
    def is_auto(self) -> bool:
        return self in _AUTO_LIKE

    def base_mode(self, armed: bool) -> int:
        """HEARTBEAT base_mode as PX4 fills it (``control_mode.cpp`` flags)."""
        flags = MODE_FLAG_CUSTOM_MODE_ENABLED
        if self in _AUTO_LIKE:
            flags |= MODE_FLAG_AUTO_ENABLED | MODE_FLAG_GUIDED_ENABLED | MODE_FLAG_STABILIZE_ENABLED
        elif self is NavState.OFFBOARD:
            flags |= MODE_FLAG_STABILIZE_ENABLED
        elif self in (NavState.MANUAL, NavState.ALTCTL, NavState.POSCTL, NavState.STAB, NavState.ACRO):
            flags |= MODE_FLAG_MANUAL_INPUT_ENABLED
            if self is not NavState.MANUAL and self is not NavState.ACRO:
                flags |= MODE_FLAG_STABILIZE_ENABLED
        if armed:
            flags |= MODE_FLAG_SAFETY_ARMED
        return flags


_AUTO_LIKE: Final = frozenset(
    {
        NavState.AUTO_MISSION,
        NavState.AUTO_LOITER,
        NavState.AUTO_RTL,
        NavState.AUTO_TAKEOFF,
        NavState.AUTO_LAND,
        NavState.DESCEND,
    }
)

#: Modes that need a pilot (RC or joystick). With COM_RC_IN_MODE=1 and no MANUAL_CONTROL they cannot
#: run, as in plain PX4 SITL.
MANUAL_MODES: Final = frozenset(
    {NavState.MANUAL, NavState.ALTCTL, NavState.POSCTL, NavState.STAB, NavState.ACRO}
)


def nav_state_from_mode(main_mode: int, sub_mode: int) -> NavState | None:
    """DO_SET_MODE's (main, sub) -> nav state, or None for modes PX4 rejects as unknown."""
    if main_mode == MAIN_AUTO:
        if sub_mode == 0:
            return NavState.AUTO_MISSION  # PX4: AUTO with sub 0 means Mission
        return {
            SUB_AUTO_TAKEOFF: NavState.AUTO_TAKEOFF,
            SUB_AUTO_LOITER: NavState.AUTO_LOITER,
            SUB_AUTO_MISSION: NavState.AUTO_MISSION,
            SUB_AUTO_RTL: NavState.AUTO_RTL,
            SUB_AUTO_LAND: NavState.AUTO_LAND,
        }.get(sub_mode)
    return {
        MAIN_MANUAL: NavState.MANUAL,
        MAIN_ALTCTL: NavState.ALTCTL,
        MAIN_POSCTL: NavState.POSCTL,
        MAIN_ACRO: NavState.ACRO,
        MAIN_OFFBOARD: NavState.OFFBOARD,
        MAIN_STABILIZED: NavState.STAB,
    }.get(main_mode)
