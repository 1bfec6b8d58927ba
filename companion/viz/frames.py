"""The frame ids of the live view and the logs, and the rotations into them.

The service works in NED and body FRD (:mod:`companion.kernel.frames`); Foxglove's 3D panel, like ROS,
expects z up, so the views use:

* ``world``: ENU (x east, y north, z up), origin at the follower's local NED origin (its home);
* ``follower``: the follower's body, FLU (x forward, y left, z up), origin at its centre;
* ``camera``: the colour camera's optical frame (x right, y down, z forward), as the images are;
* ``leader``: the tracked leader's estimated centre (axes of ``world``).

In a formation each follower's frames are prefixed with its vehicle id (``follower2/camera``); ``world`` is
shared and each follower's origin is placed in it.
"""

from __future__ import annotations

import numpy as np

from companion.kernel.frames import Mat3, Vec3

WORLD = "world"
FOLLOWER = "follower"
CAMERA = "camera"
LEADER = "leader"

#: Maps NED vectors into ENU.
R_ENU_NED: Mat3 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Maps FRD vectors into FLU (and back: it is its own inverse).
R_FLU_FRD: Mat3 = np.diag([1.0, -1.0, -1.0])


def enu(p_ned: Vec3 | tuple[float, float, float]) -> tuple[float, float, float]:
    """A NED vector in ENU axes."""
    n, e, d = (float(c) for c in p_ned)
    return e, n, -d


def R_world_follower(R_ned_body: Mat3) -> Mat3:
    """Rotation follower (FLU) -> world (ENU) of a body -> NED attitude."""
    return R_ENU_NED @ R_ned_body @ R_FLU_FRD
