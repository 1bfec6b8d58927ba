"""The simulated GPS receiver: noise with a slowly wandering bias, failure modes, outages and jumps.

Pure: time passed in, seeded randomness. Fixes come at ``GPS_RATE_HZ`` in the world's geodetic frame; the
failure modes are those PX4 SITL's simulator honours for MAV_CMD_INJECT_FAILURE.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from sitl.physics.geo import LocalProjection

GPS_RATE_HZ = 10.0


class GpsFailure(Enum):
    """The GPS failure modes PX4 SITL's simulator honours for MAV_CMD_INJECT_FAILURE."""

    NONE = "none"
    OFF = "off"  # no data at all (the receiver is gone)
    STUCK = "stuck"  # keeps reporting the last fix
    WRONG = "wrong"  # reports a position far from the truth


class NormalDraws:
    """Standard normal draws from ``rng`` taken ``n`` at a time, drawn from numpy in blocks.

    ``Generator.standard_normal`` keeps no state between calls (no cached pair), so a block of ``k``
    draws is the sequence that ``k`` calls of one draw each would have produced: seeded runs stay
    the same, and a numpy call per sample (microseconds, against a few Python reads) is saved.
    The generator must have no other user once the first block is drawn.

    Args:
        rng: The generator (owned from now on).
        block: Draws per numpy call.
    """

    __slots__ = ("_block", "_buf", "_i", "_rng")

    def __init__(self, rng: np.random.Generator, block: int = 1000) -> None:
        self._rng = rng
        self._block = block
        self._buf: list[float] = []
        self._i = 0

    def take(self, n: int) -> list[float]:
        """The next ``n`` draws."""
        i = self._i
        j = i + n
        if j > len(self._buf):
            self._buf = self._buf[i:] + self._rng.standard_normal(max(self._block, n)).tolist()
            i, j = 0, n
        self._i = j
        return self._buf[i:j]


@dataclass(frozen=True, slots=True)
class GpsNoise:
    """GPS error model per axis: white noise plus a Gauss-Markov bias (m, m/s, s)."""

    white_h_m: float = 0.15
    bias_h_m: float = 0.12
    white_v_m: float = 0.20
    bias_v_m: float = 0.08
    bias_tau_s: float = 30.0
    vel_white_m_s: float = 0.05
    #: A Gauss-Markov bias on the horizontal velocity, per axis (m/s, s; 0: none). The estimate follows GPS's
    #: velocity, and the autopilot tracks its estimate, so the vehicle strays by it (PX4 SITL's profile).
    vel_bias_m_s: float = 0.0
    vel_bias_tau_s: float = 3.0
    eph_m: float = 0.8
    epv_m: float = 1.2
    satellites: int = 14


@dataclass(frozen=True, slots=True)
class GpsSample:
    """One receiver output (geodetic, velocity NED) with its quality figures."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    vn_m_s: float
    ve_m_s: float
    vd_m_s: float
    eph_m: float
    epv_m: float
    fix_type: int
    satellites: int


@dataclass(frozen=True, slots=True)
class GpsJump:
    """A scripted GPS position error: ``offset_ned_m`` added from ``start_s`` for ``duration_s``."""

    start_s: float
    duration_s: float
    offset_ned_m: tuple[float, float, float]


@dataclass(slots=True)
class GpsOutage:
    """A scripted failure window (``end_s`` None = permanent)."""

    start_s: float
    end_s: float | None
    kind: GpsFailure


class GpsSensor:
    """A GNSS receiver at 10 Hz in the shared world frame, with noise, jumps and failures.

    Args:
        world: Projection of the world NED frame (true positions are world NED).
        rng: Seeded generator; the sensor owns it so that repeats are exact.
        noise: Error model.
        outages: Scripted failure windows (scenario); injected failures override them.
        jumps: Scripted position errors (scenario).
    """

    WRONG_OFFSET_NED_M = (120.0, -80.0, 0.0)

    def __init__(
        self,
        world: LocalProjection,
        rng: np.random.Generator,
        *,
        noise: GpsNoise | None = None,
        outages: tuple[GpsOutage, ...] = (),
        jumps: tuple[GpsJump, ...] = (),
        first_fix_s: float = 0.5,
    ) -> None:
        self._world = world
        self._normals = NormalDraws(rng, block=900)
        self.noise = noise or GpsNoise()
        self._outages = outages
        self._jumps = jumps
        self._first_fix_s = first_fix_s
        self._bias = [0.0, 0.0, 0.0]
        self._vel_bias = [0.0, 0.0]
        self._next_s = first_fix_s
        self._last: GpsSample | None = None
        #: Failure set through MAV_CMD_INJECT_FAILURE (None: the scenario decides).
        self.injected: GpsFailure | None = None

    def failure(self, t_s: float) -> GpsFailure:
        if self.injected is not None:
            return self.injected
        for o in self._outages:
            if o.start_s <= t_s and (o.end_s is None or t_s < o.end_s):
                return o.kind
        return GpsFailure.NONE

    def sample(
        self, t_s: float, p_world_ned_m: tuple[float, float, float], v_ned_m_s: tuple[float, float, float]
    ) -> GpsSample | None:
        """A new fix if one is due at ``t_s`` (call at >= 10 Hz), else None."""
        if t_s + 1e-9 < self._next_s:
            return None
        period_s = 1.0 / GPS_RATE_HZ
        self._next_s += period_s
        if self._next_s < t_s:  # caller skipped ahead: do not burst
            self._next_s = t_s + period_s
        nz = self.noise
        # Gauss-Markov bias: exact discretisation, stationary std = bias_*.
        a = math.exp(-period_s / nz.bias_tau_s)
        s = math.sqrt(1.0 - a * a)
        r = self._normals.take(9)
        self._bias[0] = a * self._bias[0] + s * nz.bias_h_m * r[0]
        self._bias[1] = a * self._bias[1] + s * nz.bias_h_m * r[1]
        self._bias[2] = a * self._bias[2] + s * nz.bias_v_m * r[2]
        vb = self._vel_bias
        if nz.vel_bias_m_s > 0.0:  # its own draws, taken only when on: a sensor without it repeats exactly
            av = math.exp(-period_s / nz.vel_bias_tau_s)
            sv = math.sqrt(1.0 - av * av) * nz.vel_bias_m_s
            rv = self._normals.take(2)
            vb[0] = av * vb[0] + sv * rv[0]
            vb[1] = av * vb[1] + sv * rv[1]
        failure = self.failure(t_s)
        if failure is GpsFailure.OFF:
            return None
        if failure is GpsFailure.STUCK and self._last is not None:
            last = self._last
            stuck = GpsSample(
                t_s, last.lat_deg, last.lon_deg, last.alt_m, last.vn_m_s, last.ve_m_s, last.vd_m_s,
                last.eph_m, last.epv_m, last.fix_type, last.satellites,
            )  # fmt: skip
            return stuck
        n = p_world_ned_m[0] + self._bias[0] + nz.white_h_m * r[3]
        e = p_world_ned_m[1] + self._bias[1] + nz.white_h_m * r[4]
        d = p_world_ned_m[2] + self._bias[2] + nz.white_v_m * r[5]
        for j in self._jumps:
            if j.start_s <= t_s < j.start_s + j.duration_s:
                n += j.offset_ned_m[0]
                e += j.offset_ned_m[1]
                d += j.offset_ned_m[2]
        if failure is GpsFailure.WRONG:
            n += self.WRONG_OFFSET_NED_M[0]
            e += self.WRONG_OFFSET_NED_M[1]
        lat, lon, alt = self._world.to_geodetic(n, e, d)
        out = GpsSample(
            t_s=t_s,
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            vn_m_s=v_ned_m_s[0] + vb[0] + nz.vel_white_m_s * r[6],
            ve_m_s=v_ned_m_s[1] + vb[1] + nz.vel_white_m_s * r[7],
            vd_m_s=v_ned_m_s[2] + nz.vel_white_m_s * r[8],
            eph_m=nz.eph_m,
            epv_m=nz.epv_m,
            fix_type=3,
            satellites=nz.satellites,
        )
        self._last = out
        return out
