"""Training augmentations (numpy + OpenCV), each a pure function of its inputs and a seeded generator.

Geometry: mosaic (four images around a random centre), a single image at a random scale and position, or the
service's tracking window on a labelled leader (magnified as at run time); horizontal flips. Appearance,
covering what real cameras do to a frame: HSV jitter, exposure (gain and gamma), white balance (per-channel
gains), defocus (disc), Gaussian or motion blur, sensor noise (shot and read noise), JPEG artefacts and
video-codec-like artefacts (4:2:0 chroma, coarse quantisation), greyscale, cut-outs (random occluders), and
copy-paste: labelled objects of another image (a real drone with its label's margin of sky or trees) blended
onto the sample, so each real drone is seen on many backgrounds and beside the birds and aircraft of the
drone-free frames. Boxes follow the geometry; a box that is mostly cut away loses its label *and* its pixels
are greyed out, so the network never sees an unlabelled leader as background.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.lab.training.cache import ImageCache
from companion.perception.detector.dataset import Boxes
from companion.perception.detector.letterbox import PAD_VALUE, resize_image
from companion.perception.detector.postprocess import box_iou

Image = NDArray[np.uint8]


@dataclass(frozen=True)
class AugmentConfig:
    """Probabilities and ranges of the augmentations (defaults: the shipped model's recipe)."""

    mosaic_p: float = 0.6
    #: Image scale relative to the letterbox fit (1.0 = the whole frame fills the input, as at run time).
    scale_range: tuple[float, float] = (0.5, 1.6)
    mosaic_scale_range: tuple[float, float] = (0.4, 1.0)
    hflip_p: float = 0.5
    hsv_gain: tuple[float, float, float] = (0.02, 0.6, 0.45)
    blur_p: float = 0.25
    noise_p: float = 0.3
    jpeg_p: float = 0.3
    gray_p: float = 0.05
    cutout_p: float = 0.4
    exposure_p: float = 0.0
    white_balance_p: float = 0.0
    codec_p: float = 0.0
    #: Blur includes defocus (a disc) and noise includes shot noise (off: Gaussian/motion blur, read noise).
    camera_model: bool = False
    #: Keep a clipped box only when this much of its area stays inside and it is this big.
    min_visible_fraction: float = 0.35
    min_box_px: float = 2.0
    #: Copy-paste (needs a donor source): probability per sample, and the donor's scale relative to its
    #: run-time size.
    paste_p: float = 0.0
    paste_scale_range: tuple[float, float] = (0.7, 1.4)
    #: The tracking window's view of a labelled leader (:func:`window_view`), probability per sample that is
    #: not a mosaic; its magnification (network px per frame px), box multiple, smallest width (frame px),
    #: a camera frame's longer side (px) and motion blur (frame px, before magnification).
    window_p: float = 0.0
    window_magnification: tuple[float, float] = (1.5, 2.0)
    window_box_multiple: float = 3.0
    window_min_px: float = 128.0
    window_frame_px: float = 640.0
    window_motion_blur_px: tuple[float, float] = (1.0, 3.0)


def place_boxes(
    canvas: Image,
    boxes: Boxes,
    region: tuple[int, int, int, int],
    *,
    min_visible_fraction: float,
    min_box_px: float,
) -> Boxes:
    """Clip boxes (canvas px) to ``region`` (x0, y0, x1, y1); drop the mostly-hidden and tiny ones.

    A dropped box that still shows pixels is greyed out on ``canvas``.
    """
    if len(boxes) == 0:
        return boxes.reshape(0, 4)
    x0, y0, x1, y1 = region
    clipped = boxes.copy()
    np.clip(clipped[:, 0::2], x0, x1, out=clipped[:, 0::2])  # views: columns 0, 2 and 1, 3
    np.clip(clipped[:, 1::2], y0, y1, out=clipped[:, 1::2])
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    w, h = clipped[:, 2] - clipped[:, 0], clipped[:, 3] - clipped[:, 1]
    keep = (w * h >= min_visible_fraction * np.maximum(area, 1e-6)) & (w >= min_box_px) & (h >= min_box_px)
    for b in clipped[~keep]:
        bx0, by0 = int(np.floor(b[0])), int(np.floor(b[1]))
        bx1, by1 = int(np.ceil(b[2])), int(np.ceil(b[3]))
        if bx1 > bx0 and by1 > by0:
            canvas[by0:by1, bx0:bx1] = PAD_VALUE
    return clipped[keep]


def random_placement(
    img: Image,
    boxes: Boxes,
    *,
    size_px: int,
    ref_px: int,
    scale: float,
    rng: np.random.Generator,
    cfg: AugmentConfig,
) -> tuple[Image, Boxes]:
    """One image at a random position on a ``size_px`` square canvas (cropped when it does not fit).

    ``scale`` is relative to the letterbox fit at ``ref_px`` (1.0: the image's longer side is ``ref_px``).
    """
    h, w = img.shape[:2]
    f = scale * ref_px / max(h, w)
    nw, nh = max(1, round(w * f)), max(1, round(h * f))
    return _on_canvas(resize_image(img, nw, nh), boxes * np.float32(f), size_px=size_px, rng=rng, cfg=cfg)


def _on_canvas(
    resized: Image, boxes: Boxes, *, size_px: int, rng: np.random.Generator, cfg: AugmentConfig
) -> tuple[Image, Boxes]:
    """``resized`` (boxes in its pixels) at a random position on a ``size_px`` square canvas."""
    nh, nw = resized.shape[:2]
    canvas = np.full((size_px, size_px, 3), PAD_VALUE, np.uint8)
    # Offset of the resized image's top-left corner on the canvas (negative: the image is cropped).
    ox = int(rng.integers(min(0, size_px - nw), max(0, size_px - nw) + 1))
    oy = int(rng.integers(min(0, size_px - nh), max(0, size_px - nh) + 1))
    sx0, sy0 = max(0, -ox), max(0, -oy)
    dx0, dy0 = max(0, ox), max(0, oy)
    cw, ch = min(nw - sx0, size_px - dx0), min(nh - sy0, size_px - dy0)
    canvas[dy0 : dy0 + ch, dx0 : dx0 + cw] = resized[sy0 : sy0 + ch, sx0 : sx0 + cw]
    b = boxes + np.array([ox, oy, ox, oy], np.float32)
    region = (dx0, dy0, dx0 + cw, dy0 + ch)
    kept = place_boxes(
        canvas, b, region, min_visible_fraction=cfg.min_visible_fraction, min_box_px=cfg.min_box_px
    )
    return canvas, kept


def window_view(
    img: Image, boxes: Boxes, *, size_px: int, ref_px: int, rng: np.random.Generator, cfg: AugmentConfig
) -> tuple[Image, Boxes] | None:
    """The service's window on a tracked leader (:mod:`companion.perception.detector.roi`), on a canvas.

    A window of ``window_box_multiple`` box widths (at least ``window_min_px`` frame pixels) at the frame's
    aspect, centred on one labelled box with the tracker's few-pixel error, enlarged bilinearly by a
    magnification drawn from ``window_magnification`` network px per frame px (the run time's 1.75x with
    some spread; the window's input stays at most ``ref_px``), then, half the time, the short motion blur
    of a follower turning during the exposure at that scale. A camera frame's longer side is
    ``window_frame_px``; cached images are smaller, so sizes scale by the ratio. None: no box, or the
    window would cover most of the frame (the service then searches the whole frame).
    """
    if len(boxes) == 0:
        return None
    h, w = img.shape[:2]
    k = max(h, w) / cfg.window_frame_px  # cached px per camera-frame px
    x0, y0, x1, y1 = (float(v) for v in boxes[int(rng.integers(len(boxes)))])
    bw, bh = x1 - x0, y1 - y0
    ww = max(cfg.window_min_px * k, cfg.window_box_multiple * max(bw, bh * w / h))
    if ww > 0.6 * w:
        return None
    wh = min(float(h), ww * h / w)
    cx = (x0 + x1) / 2 + rng.normal(0.0, 0.1) * bw
    cy = (y0 + y1) / 2 + rng.normal(0.0, 0.1) * bh
    wx = round(min(max(cx - ww / 2, 0.0), w - ww))
    wy = round(min(max(cy - wh / 2, 0.0), h - wh))
    iw, ih = max(1, round(ww)), max(1, round(wh))
    crop = img[wy : wy + ih, wx : wx + iw]
    mag = min(float(rng.uniform(*cfg.window_magnification)), ref_px * k / iw)  # network px per frame px
    f = mag / k
    nw, nh = max(1, round(crop.shape[1] * f)), max(1, round(crop.shape[0] * f))
    resized = resize_image(np.ascontiguousarray(crop), nw, nh)
    if rng.random() < 0.5:
        resized = motion_blur(resized, mag * rng.uniform(*cfg.window_motion_blur_px), rng.uniform(0, 180))
    b = (boxes - np.array([wx, wy, wx, wy], np.float32)) * np.float32(f)
    return _on_canvas(resized, b, size_px=size_px, rng=rng, cfg=cfg)


def mosaic(
    images: list[Image],
    boxes: list[Boxes],
    *,
    size_px: int,
    ref_px: int,
    rng: np.random.Generator,
    cfg: AugmentConfig,
) -> tuple[Image, Boxes]:
    """Four images meeting at a random centre of a ``size_px`` canvas; each is cropped to its quadrant.

    Image scales are relative to the letterbox fit at ``ref_px``.
    """
    canvas = np.full((size_px, size_px, 3), PAD_VALUE, np.uint8)
    xc = int(rng.uniform(0.3, 0.7) * size_px)
    yc = int(rng.uniform(0.3, 0.7) * size_px)
    out: list[Boxes] = []
    for q, (img, bx) in enumerate(zip(images, boxes, strict=True)):
        h, w = img.shape[:2]
        f = rng.uniform(*cfg.mosaic_scale_range) * ref_px / max(h, w)
        nw, nh = max(1, round(w * f)), max(1, round(h * f))
        resized = resize_image(img, nw, nh)
        right, bottom = q in (1, 3), q in (2, 3)
        # Quadrant on the canvas, and which corner of the image touches the centre.
        qx0, qx1 = (xc, size_px) if right else (0, xc)
        qy0, qy1 = (yc, size_px) if bottom else (0, yc)
        ox = xc if right else xc - nw
        oy = yc if bottom else yc - nh
        rx0, ry0 = max(qx0, ox), max(qy0, oy)
        rx1, ry1 = min(qx1, ox + nw), min(qy1, oy + nh)
        if rx1 <= rx0 or ry1 <= ry0:
            continue
        canvas[ry0:ry1, rx0:rx1] = resized[ry0 - oy : ry1 - oy, rx0 - ox : rx1 - ox]
        b = bx * np.float32(f) + np.array([ox, oy, ox, oy], np.float32)
        out.append(
            place_boxes(
                canvas,
                b,
                (rx0, ry0, rx1, ry1),
                min_visible_fraction=cfg.min_visible_fraction,
                min_box_px=cfg.min_box_px,
            )
        )
    return canvas, (np.concatenate(out) if out else np.zeros((0, 4), np.float32))


def paste_object(
    canvas: Image,
    boxes: Boxes,
    donor: Image,
    donor_box: NDArray[np.float32],
    *,
    scale: float,
    rng: np.random.Generator,
) -> Boxes:
    """Blend ``donor_box`` of ``donor`` (px) onto ``canvas`` at ``scale``; returns ``boxes`` plus its new box.

    The pasted box keeps the donor label's own margin; a ring around it (a quarter of its shorter side)
    fades from the donor's pixels to the canvas's, and the patch takes the ring's mean colour from the
    canvas, so no patch edge or colour marks it. It goes where it overlaps no box already on the canvas;
    when it fits nowhere (five tries) the canvas is left unchanged.
    """
    bw, bh = float(donor_box[2] - donor_box[0]), float(donor_box[3] - donor_box[1])
    pw, ph = round(bw * scale), round(bh * scale)
    ring = max(1, round(0.25 * min(pw, ph)))
    tw, th = pw + 2 * ring, ph + 2 * ring
    size_h, size_w = canvas.shape[:2]
    if pw < 3 or ph < 3 or tw >= size_w or th >= size_h:
        return boxes
    for _ in range(5):
        x0, y0 = int(rng.integers(0, size_w - tw + 1)), int(rng.integers(0, size_h - th + 1))
        footprint = np.array([[x0, y0, x0 + tw, y0 + th]], np.float32)
        if len(boxes) == 0 or not box_iou(footprint, boxes).any():
            break
    else:
        return boxes
    # The donor region with the ring around it, resampled so the label box becomes pw x ph.
    fx, fy = pw / max(bw, 1e-6), ph / max(bh, 1e-6)
    m = np.array([[fx, 0.0, ring - donor_box[0] * fx], [0.0, fy, ring - donor_box[1] * fy]], np.float64)
    patch = cv2.warpAffine(donor, m, (tw, th), flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REFLECT)
    # Alpha 1 on the box, falling linearly to 0 across the ring.
    ramp_x = np.minimum(np.arange(tw) + 0.5, tw - np.arange(tw) - 0.5) / ring
    ramp_y = np.minimum(np.arange(th) + 0.5, th - np.arange(th) - 0.5) / ring
    alpha = np.clip(np.minimum(ramp_y[:, None], ramp_x[None, :]), 0.0, 1.0).astype(np.float32)[..., None]
    new = np.array([x0 + ring, y0 + ring, x0 + ring + pw, y0 + ring + ph], np.float32)
    region = canvas[y0 : y0 + th, x0 : x0 + tw]
    # Shift the patch's colour so its ring matches the canvas there: a sky-blue patch on grey sky would
    # otherwise be a blob the network could learn instead of the drone.
    edge = alpha[..., 0] < 1.0
    shift = region[edge].mean(axis=0) - patch[edge].mean(axis=0)
    patch = np.clip(patch + shift, 0.0, 255.0)
    region[:] = (patch * alpha + region * (1.0 - alpha) + 0.5).astype(np.uint8)
    return np.concatenate([boxes.reshape(-1, 4), new[None]]).astype(np.float32)


def hflip(img: Image, boxes: Boxes) -> tuple[Image, Boxes]:
    """Mirror left-right."""
    w = img.shape[1]
    b = boxes.copy()
    b[:, 0], b[:, 2] = w - boxes[:, 2], w - boxes[:, 0]
    return np.ascontiguousarray(img[:, ::-1]), b


def hsv_jitter(img: Image, rng: np.random.Generator, gains: tuple[float, float, float]) -> Image:
    """Random hue, saturation and value gains through lookup tables."""
    r = rng.uniform(-1.0, 1.0, 3) * np.asarray(gains) + 1.0
    hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
    x = np.arange(256, dtype=np.float32)
    lut_h = ((x * r[0]) % 180).astype(np.uint8)
    lut_s = np.clip(x * r[1], 0, 255).astype(np.uint8)
    lut_v = np.clip(x * r[2], 0, 255).astype(np.uint8)
    hsv = cv2.merge((cv2.LUT(hsv[..., 0], lut_h), cv2.LUT(hsv[..., 1], lut_s), cv2.LUT(hsv[..., 2], lut_v)))
    return np.asarray(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), np.uint8)


#: The appearance recipe for mixed real and rendered training (real cameras: exposure, white balance,
#: codec artefacts, noise, blur).
REAL_CAMERA = AugmentConfig(
    mosaic_p=0.5,
    scale_range=(0.6, 1.6),
    mosaic_scale_range=(0.5, 1.0),
    hsv_gain=(0.015, 0.5, 0.3),
    blur_p=0.3,
    noise_p=0.35,
    jpeg_p=0.25,
    gray_p=0.05,
    cutout_p=0.2,
    exposure_p=0.5,
    white_balance_p=0.4,
    codec_p=0.3,
    camera_model=True,
)


#: ``REAL_CAMERA`` plus the tracking window's view of the leader (:func:`window_view`) for a third of the
#: samples that are not mosaics: the leader at the size and softness the service's window shows it.
REAL_CAMERA_WINDOW = replace(REAL_CAMERA, window_p=0.35)


def exposure(img: Image, rng: np.random.Generator) -> Image:
    """Exposure gain (0.6-1.5x) and gamma (0.7-1.4) through one lookup table."""
    gain, gamma = rng.uniform(0.6, 1.5), rng.uniform(0.7, 1.4)
    x = np.arange(256, dtype=np.float32) / 255.0
    lut = np.clip(255.0 * np.clip(x * gain, 0.0, 1.0) ** gamma, 0, 255).astype(np.uint8)
    return np.asarray(cv2.LUT(img, lut), np.uint8)


def white_balance(img: Image, rng: np.random.Generator) -> Image:
    """Per-channel gains of 0.85-1.15 (a camera's white balance off by a few hundred kelvin)."""
    gains = rng.uniform(0.85, 1.15, 3).astype(np.float32)
    out: Image = np.clip(img.astype(np.float32) * gains, 0, 255).astype(np.uint8)
    return out


def codec(img: Image, rng: np.random.Generator) -> Image:
    """Video-codec-like artefacts: chroma at half resolution (4:2:0), then coarse JPEG (quality 15-45)."""
    h, w = img.shape[:2]
    ycc = cv2.cvtColor(img, cv2.COLOR_RGB2YCrCb)
    small = cv2.resize(ycc[..., 1:], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA)
    ycc[..., 1:] = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    rgb = np.asarray(cv2.cvtColor(ycc, cv2.COLOR_YCrCb2RGB), np.uint8)
    ok, buf = cv2.imencode(".jpg", rgb, (cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(15, 46))))
    return np.asarray(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), np.uint8) if ok else rgb


def defocus(img: Image, radius_px: float) -> Image:
    """Convolution with a disc of ``radius_px`` (an out-of-focus lens)."""
    r = max(1, int(np.ceil(radius_px)))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    kernel = (xx**2 + yy**2 <= radius_px**2 + 0.5).astype(np.float32)
    kernel /= kernel.sum()
    return np.asarray(cv2.filter2D(img, -1, kernel), np.uint8)


def blur(img: Image, rng: np.random.Generator, with_defocus: bool = True) -> Image:
    """Gaussian blur, defocus (a disc; ``with_defocus``) or a short linear motion blur at a random angle."""
    u = rng.random()
    if u < (0.35 if with_defocus else 0.5):
        sigma = rng.uniform(0.4, 1.4)
        return np.asarray(cv2.GaussianBlur(img, (0, 0), sigma), np.uint8)
    if with_defocus and u < 0.55:
        return defocus(img, rng.uniform(1.0, 2.0))
    return motion_blur(img, float(rng.integers(3, 8)), float(rng.uniform(0, 180)))


def motion_blur(img: Image, length_px: float, angle_deg: float) -> Image:
    """A linear motion blur ``length_px`` long (rounded, at least 2 px to do anything) at ``angle_deg``."""
    length = round(length_px)
    if length < 2:
        return img
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0 / length
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle_deg, 1.0)
    kernel = np.asarray(cv2.warpAffine(kernel, rot, (length, length)), np.float32)
    kernel /= max(float(kernel.sum()), 1e-6)
    return np.asarray(cv2.filter2D(img, -1, kernel), np.uint8)


def sensor_noise(img: Image, rng: np.random.Generator, shot: bool = True) -> Image:
    """Read noise (Gaussian, sigma 2-8 grey levels); ``shot``: half the time plus brightness-scaled noise."""
    if not shot:
        gauss = rng.normal(0.0, rng.uniform(2.0, 8.0), img.shape).astype(np.float32)
        plain: Image = np.clip(img.astype(np.float32) + gauss, 0, 255).astype(np.uint8)
        return plain
    x = img.astype(np.float32)
    sigma = np.float32(rng.uniform(2.0, 8.0))
    if rng.random() < 0.5:
        sigma = np.sqrt(sigma**2 + x * np.float32(rng.uniform(0.02, 0.15)))
    noise = rng.standard_normal(img.shape).astype(np.float32) * sigma
    out: Image = np.clip(x + noise, 0, 255).astype(np.uint8)
    return out


def jpeg(img: Image, rng: np.random.Generator) -> Image:
    """Round trip through JPEG at quality 30-90 (video-compression-like artefacts)."""
    ok, buf = cv2.imencode(".jpg", img, (cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 91))))
    return np.asarray(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), np.uint8) if ok else img


def grey(img: Image) -> Image:
    """Greyscale in three channels."""
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.repeat(g[..., None], 3, axis=2)


def cutout(img: Image, boxes: Boxes, rng: np.random.Generator) -> Boxes:
    """One to three random occluders (flat colour or noise), in place; drops boxes they hide by > 60%."""
    s = img.shape[0]
    keep = np.ones(len(boxes), bool)
    for _ in range(int(rng.integers(1, 4))):
        cw, ch = (int(v) for v in rng.uniform(0.04, 0.25, 2) * s)
        x0, y0 = int(rng.integers(0, s - cw + 1)), int(rng.integers(0, s - ch + 1))
        if rng.random() < 0.5:
            img[y0 : y0 + ch, x0 : x0 + cw] = rng.integers(0, 256, 3, dtype=np.uint8)
        else:
            img[y0 : y0 + ch, x0 : x0 + cw] = rng.integers(0, 256, (ch, cw, 3), dtype=np.uint8)
        if len(boxes):
            iw = np.clip(np.minimum(boxes[:, 2], x0 + cw) - np.maximum(boxes[:, 0], x0), 0, None)
            ih = np.clip(np.minimum(boxes[:, 3], y0 + ch) - np.maximum(boxes[:, 1], y0), 0, None)
            area = np.maximum((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]), 1e-6)
            hidden = iw * ih / area > 0.6
            for b in boxes[hidden & keep]:
                img[int(b[1]) : int(np.ceil(b[3])), int(b[0]) : int(np.ceil(b[2]))] = PAD_VALUE
            keep &= ~hidden
    return boxes[keep]


def training_sample(
    cache: ImageCache,
    index: int,
    *,
    size_px: int,
    ref_px: int,
    rng: np.random.Generator,
    cfg: AugmentConfig,
    donors: ImageCache | None = None,
) -> tuple[Image, Boxes]:
    """An augmented ``size_px`` square RGB image and its leader boxes (px) from cache item ``index``.

    Objects keep the scale they have at run time with input size ``ref_px`` (times the scale jitter), so a
    ``size_px`` smaller than ``ref_px`` trains on crops: the same objects, fewer pixels, less CPU.
    ``donors``: the labelled objects copy-paste takes (``cfg.paste_p``), before the appearance changes so
    the pasted object is exposed, blurred and compressed with its new background.
    """
    if rng.random() < cfg.mosaic_p:
        idx = [index, *(int(i) for i in rng.integers(0, len(cache), 3))]
        img, boxes = mosaic(
            [cache.image(i) for i in idx],
            [cache.boxes(i) for i in idx],
            size_px=size_px,
            ref_px=ref_px,
            rng=rng,
            cfg=cfg,
        )
    else:
        placed = None
        if cfg.window_p and rng.random() < cfg.window_p:
            placed = window_view(
                cache.image(index), cache.boxes(index), size_px=size_px, ref_px=ref_px, rng=rng, cfg=cfg
            )
        img, boxes = placed or random_placement(
            cache.image(index),
            cache.boxes(index),
            size_px=size_px,
            ref_px=ref_px,
            scale=rng.uniform(*cfg.scale_range),
            rng=rng,
            cfg=cfg,
        )
    if rng.random() < cfg.hflip_p:
        img, boxes = hflip(img, boxes)
    if rng.random() < cfg.cutout_p:
        boxes = cutout(img, boxes, rng)
    if donors is not None and len(donors.labelled) and rng.random() < cfg.paste_p:
        j = int(donors.labelled[rng.integers(len(donors.labelled))])
        donor, donor_boxes = donors.image(j), donors.boxes(j)
        scale = rng.uniform(*cfg.paste_scale_range) * ref_px / max(donor.shape[:2])
        boxes = paste_object(
            img, boxes, donor, donor_boxes[rng.integers(len(donor_boxes))], scale=scale, rng=rng
        )
    img = hsv_jitter(img, rng, cfg.hsv_gain)
    if cfg.exposure_p and rng.random() < cfg.exposure_p:
        img = exposure(img, rng)
    if cfg.white_balance_p and rng.random() < cfg.white_balance_p:
        img = white_balance(img, rng)
    if rng.random() < cfg.gray_p:
        img = grey(img)
    if rng.random() < cfg.blur_p:
        img = blur(img, rng, cfg.camera_model)
    if rng.random() < cfg.noise_p:
        img = sensor_noise(img, rng, cfg.camera_model)
    if cfg.codec_p and rng.random() < cfg.codec_p:
        img = codec(img, rng)
    elif rng.random() < cfg.jpeg_p:
        img = jpeg(img, rng)
    return img, boxes.astype(np.float32)
