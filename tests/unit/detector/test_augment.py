from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from companion.lab.training.augment import (
    AugmentConfig,
    cutout,
    hflip,
    mosaic,
    paste_object,
    place_boxes,
    random_placement,
    training_sample,
)
from companion.lab.training.cache import ImageCache
from companion.lab.training.train_data import AugmentedSet
from companion.perception.detector.dataset import find_samples

GEOMETRY_ONLY = AugmentConfig(hsv_gain=(0, 0, 0), blur_p=0, noise_p=0, jpeg_p=0, gray_p=0, cutout_p=0)


def _object_image(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Black image with one white rectangle; its box is the label."""
    h, w = int(rng.integers(80, 200)), int(rng.integers(80, 200))
    img = np.zeros((h, w, 3), np.uint8)
    x0, y0 = int(rng.integers(0, w - 20)), int(rng.integers(0, h - 20))
    x1, y1 = x0 + int(rng.integers(8, 20)), y0 + int(rng.integers(8, 20))
    img[y0:y1, x0:x1] = 255
    return img, np.array([[x0, y0, x1, y1]], np.float32)


def _assert_boxes_hold_the_white_pixels(img: np.ndarray, boxes: np.ndarray) -> None:
    white = img[..., 0] > 128
    covered = np.zeros_like(white)
    for x0, y0, x1, y1 in boxes:
        assert 0 <= x0 < x1 <= img.shape[1]
        assert 0 <= y0 < y1 <= img.shape[0]
        covered[int(np.floor(y0)) : int(np.ceil(y1)), int(np.floor(x0)) : int(np.ceil(x1))] = True
        inside = white[int(np.ceil(y0)) : int(y1), int(np.ceil(x0)) : int(x1)]
        assert inside.mean() > 0.5  # a labelled box shows its object
    assert not (white & ~covered).any()  # no unlabelled object pixels (dropped boxes are greyed out)


@pytest.mark.parametrize("seed", range(12))
def test_geometry_keeps_boxes_on_their_objects(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pairs = [_object_image(rng) for _ in range(4)]
    img, boxes = mosaic(
        [p[0] for p in pairs], [p[1] for p in pairs], size_px=128, ref_px=160, rng=rng, cfg=GEOMETRY_ONLY
    )
    _assert_boxes_hold_the_white_pixels(img, boxes)
    img, boxes = random_placement(
        pairs[0][0],
        pairs[0][1],
        size_px=128,
        ref_px=160,
        scale=rng.uniform(0.5, 2.0),
        rng=rng,
        cfg=GEOMETRY_ONLY,
    )
    _assert_boxes_hold_the_white_pixels(img, boxes)
    img, boxes = hflip(img, boxes)
    _assert_boxes_hold_the_white_pixels(img, boxes)


def test_mostly_clipped_box_is_dropped_and_greyed() -> None:
    canvas = np.full((50, 50, 3), 255, np.uint8)
    kept = place_boxes(
        canvas,
        np.array([[40.0, 10.0, 60.0, 20.0]], np.float32),
        (0, 0, 50, 50),
        min_visible_fraction=0.6,
        min_box_px=2.0,
    )
    assert kept.shape == (0, 4)
    assert (canvas[10:20, 40:50] == 114).all()


@pytest.mark.parametrize("seed", range(8))
def test_pasted_object_is_labelled_where_it_lands(seed: int) -> None:
    rng = np.random.default_rng(seed)
    donor, donor_boxes = _object_image(rng)
    canvas = np.zeros((128, 128, 3), np.uint8)
    canvas[10:30, 10:30] = 255  # an object already labelled on the canvas
    before = np.array([[10, 10, 30, 30]], np.float32)
    scale = float(rng.uniform(0.7, 1.5))
    boxes = paste_object(canvas, before, donor, donor_boxes[0], scale=scale, rng=rng)
    assert len(boxes) == 2
    np.testing.assert_array_equal(boxes[0], before[0])
    new = boxes[1]
    dw, dh = donor_boxes[0, 2] - donor_boxes[0, 0], donor_boxes[0, 3] - donor_boxes[0, 1]
    assert abs((new[2] - new[0]) - round(dw * scale)) < 1e-3
    assert abs((new[3] - new[1]) - round(dh * scale)) < 1e-3
    # the donor's object fills its new box, and the old object is untouched
    x0, y0, x1, y1 = (int(v) for v in new)
    assert canvas[y0 + 1 : y1 - 1, x0 + 1 : x1 - 1, 0].min() > 200
    assert (canvas[10:30, 10:30] == 255).all()
    _assert_boxes_hold_the_white_pixels(canvas, boxes)


def test_paste_takes_the_backgrounds_colour_at_its_edge() -> None:
    # A white object on a blue donor background pasted on a grey canvas: the ring blends into grey, so
    # the canvas just outside the box stays close to grey rather than turning blue.
    donor = np.zeros((60, 60, 3), np.uint8)
    donor[...] = (40, 80, 200)
    donor[25:35, 25:35] = 255
    canvas = np.full((100, 100, 3), 120, np.uint8)
    boxes = paste_object(
        canvas,
        np.zeros((0, 4), np.float32),
        donor,
        np.array([20, 20, 40, 40], np.float32),
        scale=1.0,
        rng=np.random.default_rng(0),
    )
    x0, y0, x1, _ = (int(v) for v in boxes[0])
    ring = canvas[y0 - 2 : y0, x0:x1].reshape(-1, 3).astype(float)
    assert np.abs(ring - 120).max() < 25
    # the object is shifted with its background but stays brighter than it in every channel
    assert (canvas[y0 + 8 : y0 + 12, x0 + 8 : x0 + 12].reshape(-1, 3).min(axis=0) > 120 + 40).all()


def test_paste_that_fits_nowhere_leaves_the_canvas_alone() -> None:
    canvas = np.zeros((40, 40, 3), np.uint8)
    before = np.array([[0, 0, 40, 40]], np.float32)
    out = paste_object(
        canvas,
        before,
        np.full((30, 30, 3), 255, np.uint8),
        np.array([5, 5, 15, 15], np.float32),
        scale=1.0,
        rng=np.random.default_rng(0),
    )
    np.testing.assert_array_equal(out, before)
    assert canvas.max() == 0


def test_training_sample_pastes_donor_objects(tiny_dataset: Path, tmp_path: Path) -> None:
    cache = ImageCache.build(find_samples(tiny_dataset, "train"), tmp_path, 200, progress=False)
    cfg = replace(GEOMETRY_ONLY, mosaic_p=0.0, paste_p=1.0, scale_range=(1.0, 1.0))
    plain = replace(cfg, paste_p=0.0)
    more = 0
    for i in range(len(cache)):
        with_paste = training_sample(
            cache, i, size_px=128, ref_px=128, rng=np.random.default_rng(i), cfg=cfg, donors=cache
        )[1]
        without = training_sample(
            cache, i, size_px=128, ref_px=128, rng=np.random.default_rng(i), cfg=plain, donors=cache
        )[1]
        more += len(with_paste) - len(without)
    assert len(cache.labelled) > 0
    assert more > len(cache) // 2


def test_cutout_drops_hidden_boxes_only() -> None:
    rng = np.random.default_rng(0)
    img = np.zeros((64, 64, 3), np.uint8)
    boxes = np.array([[0, 0, 64, 64], [10, 10, 12, 12]], np.float32)
    out = cutout(img, boxes, rng)
    assert len(out) >= 1
    assert any(np.array_equal(b, boxes[0]) for b in out)


def test_training_sample_is_a_pure_function_of_its_seed(tiny_dataset: Path, tmp_path: Path) -> None:
    cache = ImageCache.build(find_samples(tiny_dataset, "train"), tmp_path, 200, progress=False)
    a = training_sample(
        cache, 3, size_px=96, ref_px=128, rng=np.random.default_rng([1, 2, 3]), cfg=AugmentConfig()
    )
    b = training_sample(
        cache, 3, size_px=96, ref_px=128, rng=np.random.default_rng([1, 2, 3]), cfg=AugmentConfig()
    )
    assert a[0].shape == (96, 96, 3)
    assert a[0].dtype == np.uint8
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    # a second build finds the cache instead of decoding again
    assert (
        ImageCache.build(find_samples(tiny_dataset, "train"), tmp_path, 200, progress=False).keys
        == cache.keys
    )


def test_paste_onto_limits_which_sources_get_pasted_objects(tiny_dataset: Path, tmp_path: Path) -> None:
    cache = ImageCache.build(find_samples(tiny_dataset, "train"), tmp_path, 200, progress=False)
    cfg = replace(GEOMETRY_ONLY, mosaic_p=0.0, paste_p=1.0, scale_range=(1.0, 1.0))
    # Source 0 donates and receives; source 1 (the same images) is left alone.
    ds = AugmentedSet([cache, cache], 128, 128, 0, cfg, donor_source=0, paste_onto=frozenset({0}))
    plain = AugmentedSet([cache, cache], 128, 128, 0, replace(cfg, paste_p=0.0))
    gained = {0: 0, 1: 0}
    for source in (0, 1):
        for i in range(len(cache)):
            key = (0, source, i, 0, False)
            gained[source] += len(ds[key][1]) - len(plain[key][1])
    assert gained[0] > len(cache) // 2
    assert gained[1] == 0
