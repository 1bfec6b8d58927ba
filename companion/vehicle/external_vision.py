"""PX4's external-vision aiding (EKF2_EV_CTRL): which bits a GPS-loss policy needs, read and set on connect.

PX4 ships external-vision aiding off (0). The ``vision_external_position`` policy sends PX4 a position fix
after a GPS loss (the leader's shared position minus the seen vector); PX4 fuses it only with bit 0
(horizontal position) set. Both vehicle links add the missing bits at connect, never take any away.
"""

from __future__ import annotations

#: PX4's external-vision aiding bitmask (EKF2; 0, off, by default).
EV_CTRL_PARAM = "EKF2_EV_CTRL"


def ev_position_bits_for(gps_loss_policy: str) -> int:
    """The EKF2_EV_CTRL bits a GPS-loss policy needs PX4 to have.

    Horizontal position (bit 0) for the external-position policy, none for the others.
    """
    return 1 if gps_loss_policy == "vision_external_position" else 0
