"""The slot rule: where an operator may put the leader in the camera frame (``offset_cam_m``); pure.

One rule for every way a slot arrives: the config's ``formation.offset_cam_m``, ``companion command
set_offset``, an MQTT ``set_offset`` and the mission machine, which applies it on its tick. It lives with
the config because the config is the lowest layer all of them import.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: Farthest the slot may put the leader, m: a 0.45 m leader at 50 m spans about 4 pixels of a 640-pixel
#: image, too few for the detector to find it again once lost.
MAX_SLOT_RANGE_M = 50.0
#: Widest the slot's bearing off the camera axis may be, deg: further out the leader leaves the image as
#: soon as the follower yaws a little.
MAX_SLOT_BEARING_DEG = 30.0
#: Room kept between the slot and the separation bubble (``safety.min_separation_m``), m, so that the law
#: and the separation barrier never fight at rest.
SLOT_SEPARATION_MARGIN_M = 1.0


def slot_refusal(offset_cam_m: Sequence[float], min_separation_m: float) -> str | None:
    """Why a slot is refused, in one line (None: it is good).

    ``offset_cam_m``: the leader's place in the level camera frame (x right, y down, z forward), m;
    ``min_separation_m``: the separation the follower keeps (``safety.min_separation_m``), m.
    """
    x_right, y_down, z_forward = (float(c) for c in offset_cam_m)
    if not all(math.isfinite(c) for c in (x_right, y_down, z_forward)):
        return "offset must be finite"
    if z_forward <= 0.0:
        return "the leader must be ahead of the camera (z > 0)"
    dist = math.sqrt(x_right**2 + y_down**2 + z_forward**2)
    if dist < min_separation_m + SLOT_SEPARATION_MARGIN_M:
        return f"slot {dist:.1f} m from the leader: closer than min_separation_m + 1 m"
    if dist > MAX_SLOT_RANGE_M:
        return f"slot {dist:.1f} m from the leader: further than {MAX_SLOT_RANGE_M:g} m"
    if abs(math.atan2(x_right, z_forward)) > math.radians(MAX_SLOT_BEARING_DEG):
        return f"the leader would leave the image (more than {MAX_SLOT_BEARING_DEG:g} deg off the axis)"
    return None
