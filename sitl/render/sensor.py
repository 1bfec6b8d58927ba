"""The camera sensor's side of a frame on the CPU: exposure, white balance and the sensor model's uniforms.

The shaders apply the sensor model (``shaders.SENSOR``: stereo depth noise and holes, colour noise,
vignetting, contrast); this module folds its constants for them, draws each frame's noise offset and
seed, and meters the picture for the next frame's exposure.
"""

from __future__ import annotations

import math
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import Intrinsics
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.gl import set_uniform
from sitl.render.noise import FIELD_PX, NORMAL_RANGE

#: Auto exposure aims the frame's mean linear luminance at this (18 % grey).
AE_TARGET = 0.18
#: Exposure gain at which the shutter is fully open; above it, analog gain (and noise) rises.
GAIN_AT_MAX_SHUTTER = 2.0
#: Sd of the sum of two uniform bytes, the shaders' colour-noise unit (see ``shaders.SENSOR``).
NOISE_SUM_SD = math.sqrt(2.0 * (256.0**2 - 1.0) / 12.0)


def kelvin_rgb(kelvin: float) -> tuple[float, float, float]:
    """Approximate linear RGB of a black body (Tanner Helland's fit), green normalised to 1."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = (
        99.4708025861 * math.log(t) - 161.1195681661
        if t <= 66
        else 288.1221695283 * (t - 60) ** -0.0755148492
    )
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.0447927307)
    lin = [(min(max(c, 1.0), 255.0) / 255.0) ** 2.2 for c in (r, g, b)]
    return lin[0] / lin[1], 1.0, lin[2] / lin[1]


def white_balance_gains(camera_k: float) -> tuple[float, float, float]:
    """Per-channel gains of a camera white-balanced for ``camera_k`` kelvin under daylight (5500 K).

    A camera set for warmer light than there is boosts blue: the picture turns cold, and vice versa.
    """
    cam, ref = kelvin_rgb(camera_k), kelvin_rgb(5500.0)
    return ref[0] / cam[0], 1.0, ref[2] / cam[2]


def metered_log2_gain(log2_gain: float, rgb: NDArray[np.uint8]) -> float:
    """Auto exposure: the next frame's log2 exposure gain from this frame's picture (its mean luminance)."""
    sample = rgb[::12, ::12].astype(np.float32) * np.float32(1.0 / 255.0)
    lin = float(np.mean(sample * sample))  # the sensor encodes with gamma 2
    return min(8.0, max(-8.0, log2_gain + 0.8 * math.log2(AE_TARGET / max(lin, 1e-4))))


def sensor_constants(prog: moderngl.Program, camera: CameraModel) -> None:
    """Uniforms of the sensor model that never change for a camera (see ``shaders.SENSOR``)."""
    cam = camera
    fB = cam.focal_baseline_px_m
    sigma_px = cam.subpixel_px if cam.depth_noise else 0.0
    floor, low_texture = (0.004, 0.10) if cam.depth_holes else (0.0, 0.0)
    set_uniform(prog, "u_noise", 2)
    set_uniform(prog, "u_disp_noise", (NORMAL_RANGE * sigma_px, -0.5 * NORMAL_RANGE * sigma_px))
    set_uniform(prog, "u_drange", (fB / cam.depth_max_m, fB / cam.depth_min_m))
    set_uniform(prog, "u_hole_p", (floor + low_texture, low_texture))


def sensor_uniforms(
    rng: np.random.Generator, camera: CameraModel, visual: VisualConfig, intr: Intrinsics, analog_gain: float
) -> dict[str, Any]:
    """Per-frame sensor-model uniforms (see ``shaders.SENSOR``), constants folded for the shader.

    A fresh noise offset and colour-noise seed each frame (two draws from ``rng``). Colour noise: shot
    variance ``a`` and read variance ``b`` grow with analog gain; in the sqrt domain their sd is about
    ``0.5 sqrt(a) + 0.5 sqrt(b) / (v + b^0.25)``. Vignetting darkens by
    ``vignetting / 4 * (radius / half width)^2``; contrast pivots on 0.45.
    """
    W, H = intr.width_px, intr.height_px
    offs = rng.integers(0, FIELD_PX, 2)
    seed = int(rng.integers(0, 2**32, dtype=np.uint64))
    k = visual.sensor_noise if camera.colour_noise else 0.0
    a, b = 0.0008 * analog_gain * k, (0.002 * analog_gain * k) ** 2
    c = visual.contrast
    x, y, z = 0.5 * math.sqrt(a), 0.5 * math.sqrt(b), max(b**0.25, 1e-3)
    # The shader's noise is the hash's byte sums (sd NOISE_SUM_SD) and its read-noise term sees v g k / c.
    sd = (c * x / NOISE_SUM_SD, c * c * y / NOISE_SUM_SD, c * z)
    r_scale = math.sqrt(c * visual.vignetting / 4.0) / (W / 2.0)
    return {
        "u_off": (int(offs[0]), int(offs[1])),
        "u_seed": seed,
        "u_noise_sd": sd,
        "u_vig": (r_scale, r_scale, -r_scale * W / 2.0, -r_scale * H / 2.0),
        "u_tone": (c, 0.45 * (1.0 - c)),
    }
