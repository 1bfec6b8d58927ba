"""The real-camera augmentations: shapes, determinism, and that each does what it says."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.lab.training.augment import (
    REAL_CAMERA,
    codec,
    defocus,
    exposure,
    sensor_noise,
    training_sample,
    white_balance,
)
from companion.lab.training.cache import ImageCache
from companion.perception.detector.dataset import find_samples


def _img() -> np.ndarray:
    rng = np.random.default_rng(0)
    img = np.full((64, 80, 3), 128, np.uint8)
    img[20:30, 30:50] = rng.integers(0, 255, (10, 20, 3), dtype=np.uint8)
    return img


def test_each_keeps_shape_and_type_and_is_seeded() -> None:
    img = _img()
    for fn in (exposure, white_balance, codec, sensor_noise):
        a = fn(img, np.random.default_rng(4))
        b = fn(img, np.random.default_rng(4))
        assert a.shape == img.shape
        assert a.dtype == np.uint8
        np.testing.assert_array_equal(a, b)


def test_defocus_spreads_a_point_over_a_disc() -> None:
    img = np.zeros((21, 21, 3), np.uint8)
    img[10, 10] = 255
    out = defocus(img, 2.0)
    lit = (out[..., 0] > 0).sum()
    assert 9 <= lit <= 25
    assert out[10, 10, 0] < 255


def test_white_balance_scales_channels_independently() -> None:
    img = np.full((8, 8, 3), 100, np.uint8)
    out = white_balance(img, np.random.default_rng(1)).astype(int)
    assert len({int(out[..., c].mean()) for c in range(3)}) > 1
    assert np.all(np.abs(out - 100) <= 16)


def test_codec_halves_chroma_detail() -> None:
    img = np.full((32, 32, 3), 128, np.uint8)
    img[:, ::2, 0] = 255  # a one-pixel red stripe pattern: chroma detail that 4:2:0 cannot keep
    out = codec(img, np.random.default_rng(2)).astype(int)
    assert (
        np.abs(out[:, ::2, 0] - out[:, 1::2, 0]).mean()
        < np.abs(img[:, ::2, 0].astype(int) - img[:, 1::2, 0]).mean()
    )


def test_real_camera_recipe_is_a_pure_function_of_the_seed(tiny_dataset: Path, tmp_path: Path) -> None:
    cache = ImageCache.build(find_samples(tiny_dataset, "train"), tmp_path, 200, progress=False)
    a = training_sample(cache, 2, size_px=96, ref_px=128, rng=np.random.default_rng([5, 1]), cfg=REAL_CAMERA)
    b = training_sample(cache, 2, size_px=96, ref_px=128, rng=np.random.default_rng([5, 1]), cfg=REAL_CAMERA)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_default_recipe_draws_blur_and_noise_as_without_the_camera_model() -> None:
    img = _img()
    from companion.lab.training.augment import blur

    for seed in range(6):
        a = blur(img, np.random.default_rng(seed), with_defocus=False)
        rng = np.random.default_rng(seed)
        if rng.random() < 0.5:
            import cv2

            b = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.4, 1.4))
            np.testing.assert_array_equal(a, b)
    plain = sensor_noise(img, np.random.default_rng(3), shot=False)
    rng = np.random.default_rng(3)
    ref = np.clip(img.astype(np.float32) + rng.normal(0.0, rng.uniform(2.0, 8.0), img.shape), 0, 255)
    np.testing.assert_array_equal(plain, ref.astype(np.uint8))
