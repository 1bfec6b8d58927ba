"""Which velocity of the follower's own the tracker's ego-motion takes, sample by sample; pure.

PX4's velocity while its estimate is GPS-aided (and the drag model learns from it). After a GPS loss PX4's
dead-reckoned velocity runs off by metres per second within seconds, so the
:class:`~companion.estimation.ego_velocity.EgoVelocityObserver`'s is taken instead, from the drag model
learnt meanwhile and the attitude, with PX4's vertical velocity (the barometer keeps the height aided).
Without a model: PX4's vertical velocity alone, the horizontal held at the last aided one (the track
predicts on its own relative velocity there).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.estimation.ego_velocity import EgoVelocityObserver
from companion.kernel.flight import Vec3T
from companion.kernel.frames import Mat3, Vec3

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class OwnVelocitySample:
    """What one velocity sample gave."""

    #: The follower's velocity for perception's history (NED, m/s); None: nothing for this sample.
    v_ned_m_s: Vec3T | Vec3 | None
    #: The sample taught the drag model (its model, ``OwnVelocity.ego.model()``, may have moved).
    learnt: bool


class OwnVelocity:
    """The policy above, with the drag model it learns (``ego``)."""

    def __init__(self) -> None:
        self.ego = EgoVelocityObserver()
        self._v_aided: Vec3T | None = None
        self._said = False

    def update(
        self, stamp_s: float, v_ned_m_s: Vec3T, R_ned_body: Mat3 | None, *, aided: bool
    ) -> OwnVelocitySample:
        """One velocity sample of PX4's (NED, m/s, at ``stamp_s``, s).

        ``R_ned_body``: PX4's own attitude at the sample (None when not finite); ``aided``: the mission's
        debounced GPS verdict is good and PX4 does not call its position invalid.
        """
        if aided:
            learnt = R_ned_body is not None
            if R_ned_body is not None:
                # The model learns PX4's own attitude, heading error and all.
                self.ego.learn(stamp_s, v_ned_m_s, R_ned_body)
            self._v_aided = v_ned_m_s
            self._said = False
            return OwnVelocitySample(v_ned_m_s, learnt)
        if R_ned_body is None or self._v_aided is None:
            return OwnVelocitySample(None, False)
        if not self._said:
            self._said = True
            self._say_model()
        vd_m_s = float(v_ned_m_s[2])
        v_own = self.ego.step(stamp_s, R_ned_body, self._v_aided, vd_m_s)
        if v_own is None and math.isfinite(vd_m_s):
            # No drag model: no horizontal ego-motion (held), the vertical still PX4's.
            v_own = np.array([self._v_aided[0], self._v_aided[1], vd_m_s], dtype=np.float64)
        return OwnVelocitySample(v_own, False)

    def _say_model(self) -> None:
        """One line at a GPS loss: what the follower's velocity will come from now."""
        m = self.ego.model()
        if m is None:
            log.warning(
                "ego velocity: no drag model learnt before the GPS loss; "
                "the track predicts alone horizontally"
            )
            return
        log.info(
            "ego velocity without GPS: drag %.2f 1/s, wind push (%.2f, %.2f) m/s^2, heading error %.1f deg "
            "(%d samples)",
            m.drag_per_s,
            *m.push_ne_m_s2,
            math.degrees(m.heading_error_rad),
            m.samples,
        )
