"""The stereo-depth noise model and the precomputed noise fields the post pass samples. Pure numpy.

Per-frame noise costs nothing on the CPU: the fields are made once (periodic, 1024 x 1024), uploaded as
RGBA8 textures, and each frame samples them at a fresh random offset.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sp_fft
from numpy.typing import NDArray
from scipy.special import ndtr

U8 = NDArray[np.uint8]
F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

FIELD_PX = 1024
#: Normal noise is stored as ``byte = 255 * (n / NORMAL_RANGE + 0.5)``: +-4 sigma in 8 bits.
NORMAL_RANGE = 8.0


def depth_sigma_m(z_m: float | F64, focal_px: float, baseline_m: float, subpixel_px: float) -> float | F64:
    """RMS depth error of a D400 stereo camera at depth z: ``z^2 * subpixel / (f * B)`` (Intel's model).

    At the D435i defaults (f = 465.6 px at 640 px and 69 deg, B = 50 mm, 0.08 px) that is 14 mm at 2 m,
    86 mm at 5 m and 344 mm at 10 m.
    """
    return z_m * z_m * subpixel_px / (focal_px * baseline_m)


def _gauss_spectrum(sigma_px: float) -> F32:
    """Fourier transform of a unit-area Gaussian on the FIELD_PX grid (rfft layout)."""
    fy = np.fft.fftfreq(FIELD_PX).astype(np.float32)
    fx = np.fft.rfftfreq(FIELD_PX).astype(np.float32)
    g: F32 = np.exp(np.float32(-2.0 * (math.pi * sigma_px) ** 2) * (fy[:, None] ** 2 + fx[None, :] ** 2))
    return g


def _periodic_filter(field: F32, spectrum: F32) -> F32:
    """Filter with wrap-around (so the field tiles), via a real float32 FFT."""
    out: F32 = sp_fft.irfft2(sp_fft.rfft2(field) * spectrum, s=field.shape).astype(np.float32)
    return out


def _periodic_blur(field: F32, sigma_px: float) -> F32:
    """Gaussian blur with wrap-around."""
    return field if sigma_px <= 0 else _periodic_filter(field, _gauss_spectrum(sigma_px))


def _unit(field: F32) -> F32:
    out: F32 = (field - field.mean()) / field.std()
    return out


def _encode_normal(n: F32) -> U8:
    out: U8 = np.clip(np.rint(255.0 * (n / NORMAL_RANGE + 0.5)), 0, 255).astype(np.uint8)
    return out


def sensor_noise_field(seed: int, depth_corr_px: float, blob_px: float = 2.5) -> U8:
    """The post pass's RGBA8 noise texture (FIELD_PX x FIELD_PX x 4), sampled at a new offset per frame.

    r = white N(0, 1) luminance noise, g = white N(0, 1) chroma noise (colour sensor noise; g also
    serves as a per-pixel coin), b = N(0, 1) blurred by ``depth_corr_px`` and renormalised (stereo
    matching smears its errors over a few pixels), a = a clumpy field made uniform on [0, 1]:
    thresholding it at p drops a fraction p of pixels in blobs, as failed matches do.
    """
    rng = np.random.default_rng(seed)
    shape = (FIELD_PX, FIELD_PX)
    out = np.empty((*shape, 4), dtype=np.uint8)
    out[..., 0] = _encode_normal(rng.standard_normal(shape, dtype=np.float32))
    out[..., 1] = _encode_normal(rng.standard_normal(shape, dtype=np.float32))
    out[..., 2] = _encode_normal(
        _unit(_periodic_blur(rng.standard_normal(shape, dtype=np.float32), depth_corr_px))
    )
    blobs = ndtr(_unit(_periodic_blur(rng.standard_normal(shape, dtype=np.float32), blob_px)))
    out[..., 3] = np.clip(np.rint(blobs * 255.0), 0, 255).astype(np.uint8)
    return out


def pattern_texture(seed: int) -> U8:
    """The world's pattern texture (FIELD_PX square RGBA8, periodic): noise at four scales.

    r: large blobs (ground patches, cloud masses), g: medium, b: fine, a: white. Each channel is
    mapped through the normal CDF to uniform [0, 1] so thresholds in the shaders mean fractions of area.
    """
    rng = np.random.default_rng(seed)
    shape = (FIELD_PX, FIELD_PX)
    out = np.empty((*shape, 4), dtype=np.uint8)
    # r: fractal noise (octaves of blurred noise, halving in size and weight), made in one filtering.
    fbm_spectrum = sum(
        ((0.55**i) * (48.0 / 2.0**i) * _gauss_spectrum(48.0 / (2.0**i)) for i in range(5)),
        start=np.zeros_like(_gauss_spectrum(1.0)),
    )
    fbm = _periodic_filter(rng.standard_normal(shape, dtype=np.float32), fbm_spectrum)
    fields = (
        fbm,
        _periodic_blur(rng.standard_normal(shape, dtype=np.float32), 6.0),
        _periodic_blur(rng.standard_normal(shape, dtype=np.float32), 1.2),
    )
    for ch, field in enumerate(fields):
        out[..., ch] = np.clip(ndtr(_unit(field)) * 256.0, 0, 255).astype(np.uint8)
    out[..., 3] = rng.integers(0, 256, shape, dtype=np.uint8)
    return out
