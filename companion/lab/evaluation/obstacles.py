"""The scene's solid structures as collision envelopes, and a point's clearance from them (pure).

The renderer draws trees, buildings, poles and walls (a scenario's ``occluders`` and the world's random
structures); the simulator's physics does not know them, so a follower flying through a tree would not
crash there. The evaluation does: each structure gets a simple envelope that contains what is drawn
(a vertical cylinder for a tree's crown or a pole, a yawed box for a building with its roof, a wall, a
branch), and the truth monitor calls it a crash when the follower's centre comes within its body radius
of one. Envelopes, in world NED metres (z down, the ground at 0):

* tree: radius half the crown diameter (the crown's blobs), from the ground to the top; conifer: the
  same (its lowest cone is that wide). The trunk below the crown is inside it: conservative.
* pole: its radius (the cross-arm at the top, 7-12 m up, is left out).
* building: its footprint up to its height plus a roof of up to 0.45 x its shorter side.
* wall: its box; branch: its box where it floats.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

#: Highest a pitched roof rises above a building's walls, in units of its shorter side
#: (sitl.render.structures).
ROOF_RISE = 0.45


class StructureSpec(Protocol):
    """What the evaluation reads of ``sitl.render.config.OccluderSpec``."""

    @property
    def kind(self) -> str: ...
    @property
    def p_ned_m(self) -> tuple[float, float, float]: ...
    @property
    def yaw_deg(self) -> float: ...
    @property
    def resolved_size_m(self) -> tuple[float, float, float]: ...


@dataclass(frozen=True, slots=True)
class Envelopes:
    """Vertical cylinders and yawed boxes, world NED m; see the module doc."""

    cyl_ne_m: F64  # (n, 2) axis position
    cyl_r_m: F64  # (n,)
    cyl_z_m: F64  # (n, 2) top and bottom z (NED: top < bottom)
    cyl_kind: tuple[str, ...]
    box_centre_m: F64  # (m, 3)
    box_half_m: F64  # (m, 3) half-extents along the box's own x, y, z
    box_yaw_rad: F64  # (m,)
    box_kind: tuple[str, ...]

    @classmethod
    def from_specs(cls, specs: Iterable[StructureSpec]) -> Envelopes:
        cyl: list[tuple[float, float, float, float, float]] = []
        cyl_kind: list[str] = []
        box: list[tuple[float, float, float, float, float, float, float]] = []
        box_kind: list[str] = []
        for s in specs:
            w, d, h = s.resolved_size_m
            n, e, z = s.p_ned_m
            yaw = math.radians(s.yaw_deg)
            if s.kind in ("tree", "conifer"):
                cyl.append((n, e, 0.5 * w, -h, 0.0))
                cyl_kind.append(s.kind)
            elif s.kind == "pole":
                cyl.append((n, e, max(w, 0.05), -h, 0.0))
                cyl_kind.append(s.kind)
            elif s.kind == "branch":
                box.append((n, e, z, 0.5 * w, 0.5 * d, 0.5 * h, yaw))
                box_kind.append(s.kind)
            else:  # building, wall
                top = h + (ROOF_RISE * min(w, d) if s.kind == "building" else 0.0)
                box.append((n, e, -0.5 * top, 0.5 * w, 0.5 * d, 0.5 * top, yaw))
                box_kind.append(s.kind)
        c = np.asarray(cyl, dtype=np.float64).reshape(-1, 5)
        b = np.asarray(box, dtype=np.float64).reshape(-1, 7)
        return cls(
            c[:, 0:2], c[:, 2], c[:, 3:5], tuple(cyl_kind), b[:, 0:3], b[:, 3:6], b[:, 6], tuple(box_kind)
        )

    def __len__(self) -> int:
        return len(self.cyl_kind) + len(self.box_kind)

    def clearance(self, p_ned_m: ArrayLike) -> tuple[float, str]:
        """Signed distance from a point to the nearest envelope, m (negative inside), and its kind."""
        p = np.asarray(p_ned_m, dtype=np.float64)
        best, kind = math.inf, ""
        if self.cyl_kind:
            d_r = np.hypot(p[0] - self.cyl_ne_m[:, 0], p[1] - self.cyl_ne_m[:, 1]) - self.cyl_r_m
            z_mid = 0.5 * (self.cyl_z_m[:, 0] + self.cyl_z_m[:, 1])
            d_z = np.abs(p[2] - z_mid) - 0.5 * (self.cyl_z_m[:, 1] - self.cyl_z_m[:, 0])
            sd = np.minimum(np.maximum(d_r, d_z), 0.0) + np.hypot(np.maximum(d_r, 0.0), np.maximum(d_z, 0.0))
            i = int(np.argmin(sd))
            best, kind = float(sd[i]), self.cyl_kind[i]
        if self.box_kind:
            rel = p - self.box_centre_m
            c, s = np.cos(self.box_yaw_rad), np.sin(self.box_yaw_rad)
            # Into each box's own axes: R_ned_box = Rz(yaw), so local = R^T rel.
            local = np.stack(
                [c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1
            )
            q = np.abs(local) - self.box_half_m
            sd = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
            i = int(np.argmin(sd))
            if float(sd[i]) < best:
                best, kind = float(sd[i]), self.box_kind[i]
        return best, kind
