"""The formation-range recipe: size-trusting box loss, the tracking window's view, mined real data, and the
evaluation by range bin in the whole frame and the tracking window."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from companion.config import DetectorConfig
from companion.lab.training.augment import REAL_CAMERA, AugmentConfig, window_view
from companion.lab.training.evaluate import collect_window, range_bins
from companion.lab.training.loss import DetectionLoss, ciou, ciou_loss_parts
from companion.lab.training.metrics import DetectionStats
from companion.lab.training.mine import background_strip, false_alarms, mine_hard, write_backgrounds
from companion.lab.training.train import batch_size_weights
from companion.lab.training.train_config import DataSource, TrainConfig
from companion.perception.detector.dataset import Sample, find_samples, format_yolo_labels
from companion.perception.detector.leadernet import LeaderNet
from companion.perception.types import Detection, DetectorResult


def _box(*v: float) -> np.ndarray:
    return np.asarray([v], np.float32).reshape(-1, 4)


def test_ciou_splits_into_position_and_size_that_sum_to_it() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.rand(64, 2, generator=g) * 50
    b = torch.rand(64, 2, generator=g) * 50
    pred = torch.cat((a, a + 5 + torch.rand(64, 2, generator=g) * 30), 1)
    target = torch.cat((b, b + 5 + torch.rand(64, 2, generator=g) * 30), 1)
    position, size = ciou_loss_parts(pred, target)
    torch.testing.assert_close(position + size, 1.0 - ciou(pred, target))
    assert bool((position >= -1e-6).all())
    assert bool((size >= -1e-6).all())
    # Same centre, other size: all of it is size. Same size, moved: none of it is.
    grown = torch.tensor([[0.0, 0.0, 20.0, 20.0]])
    label = torch.tensor([[5.0, 5.0, 15.0, 15.0]])
    p, s = ciou_loss_parts(grown, label)
    assert float(p) == pytest.approx(0.0, abs=1e-6)
    assert float(s) == pytest.approx(0.75, abs=1e-4)
    moved = torch.tensor([[8.0, 5.0, 18.0, 15.0]])
    p, s = ciou_loss_parts(moved, label)
    assert float(s) == pytest.approx(0.0, abs=1e-6)
    assert float(p) > 0.3


def test_size_weight_one_is_the_plain_loss_and_zero_ignores_a_labels_extent() -> None:
    torch.manual_seed(0)
    net = LeaderNet()
    crit = DetectionLoss(net)
    feats = net(torch.rand(2, 3, 96, 96))
    boxes = torch.tensor([[[10.0, 10.0, 40.0, 30.0]], [[50.0, 40.0, 70.0, 60.0]]])
    mask = torch.ones(2, 1, dtype=torch.bool)
    plain, parts = crit(feats, boxes, mask)
    same, parts_w = crit(feats, boxes, mask, torch.ones(2))
    torch.testing.assert_close(plain, same)
    assert parts == pytest.approx(parts_w)
    # Weight 0 on every image: the edge distributions learn nothing from the labels, and the box term keeps
    # only the position part, which is 0 for a prediction that is centred but of another size.
    _, zero = crit(feats, boxes, mask, torch.zeros(2))
    assert zero["dfl"] == 0.0
    assert parts["dfl"] > 0.0
    assert zero["box"] < parts["box"]


def test_batch_size_weights_follow_the_sources_shares() -> None:
    cfg = TrainConfig(
        data="",
        out="x",
        sources=(DataSource("real", "a"), DataSource("form", "b")),
        size_weights=(("real", 0.5),),
    )
    w = batch_size_weights(cfg, ["real", "form"], [3, 2], torch.device("cpu"))
    assert w is not None
    assert w.tolist() == [0.5, 0.5, 0.5, 1.0, 1.0]
    assert (
        batch_size_weights(replace(cfg, size_weights=()), ["real", "form"], [3, 2], torch.device("cpu"))
        is None
    )
    with pytest.raises(ValueError, match="no source of that name"):
        batch_size_weights(replace(cfg, size_weights=(("sky", 0.5),)), ["real"], [5], torch.device("cpu"))


def test_window_view_shows_the_leader_at_the_windows_magnification() -> None:
    rng_img = np.random.default_rng(0)
    img = rng_img.integers(0, 255, (480, 640, 3), dtype=np.uint8)  # a camera frame at full size
    box = _box(300, 200, 330, 220)  # 30 px wide: a leader about 7 m away
    cfg = replace(REAL_CAMERA, window_magnification=(1.75, 1.75), window_motion_blur_px=(0.0, 0.0))
    widths = []
    for seed in range(10):
        out = window_view(img, box, size_px=320, ref_px=416, rng=np.random.default_rng(seed), cfg=cfg)
        assert out is not None
        canvas, boxes = out
        assert canvas.shape == (320, 320, 3)
        assert len(boxes) <= 1
        if len(boxes):
            widths.append(float(boxes[0, 2] - boxes[0, 0]))
    assert widths
    assert np.median(widths) == pytest.approx(30 * 1.75, abs=1.0)
    # The same frame cached smaller: sizes scale with it, the magnification is per camera-frame pixel.
    small = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
    out = window_view(small, box / 2, size_px=320, ref_px=416, rng=np.random.default_rng(1), cfg=cfg)
    assert out is not None
    assert len(out[1])
    assert float(out[1][0, 2] - out[1][0, 0]) == pytest.approx(52.5, abs=1.5)
    # No leader, or one so near that the window would cover most of the frame: no window view.
    assert (
        window_view(
            img, np.zeros((0, 4), np.float32), size_px=320, ref_px=416, rng=np.random.default_rng(0), cfg=cfg
        )
        is None
    )
    assert (
        window_view(
            img, _box(100, 100, 300, 250), size_px=320, ref_px=416, rng=np.random.default_rng(0), cfg=cfg
        )
        is None
    )
    assert AugmentConfig().window_p == 0.0  # off unless a recipe asks for it


def test_false_alarms_are_detections_away_from_every_label() -> None:
    labels = _box(100, 100, 140, 130)
    boxes = np.concatenate([_box(105, 105, 130, 125), _box(95, 95, 150, 140), _box(300, 50, 320, 70)])
    scores = np.asarray([0.9, 0.5, 0.4], np.float32)
    assert false_alarms(boxes, scores, labels).tolist() == pytest.approx([0.4])
    assert false_alarms(boxes, scores, np.zeros((0, 4), np.float32)).tolist() == pytest.approx(
        [0.9, 0.5, 0.4]
    )


def test_background_strip_keeps_clear_of_every_label() -> None:
    strip = background_strip(_box(500, 100, 540, 130), 640, 512)
    assert strip is not None
    x0, y0, x1, y1 = strip
    assert (x0, y0, y1) == (0, 0, 512)
    assert x1 <= 500 - 40
    assert background_strip(_box(200, 150, 440, 380), 640, 512) is None  # a large drone in the middle


def _real_folder(root: Path) -> Path:
    """A flat real-footage folder: two videos, drone frames and drone-free ones, with a manifest."""
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    rows = ["image,video,n_boxes"]
    for video in ("V_DRONE_001", "V_BIRD_002"):
        for f in range(3):
            name = f"{video}_f{f:05d}"
            img = np.full((256, 320, 3), 180, np.uint8)
            boxes = _box(250, 30, 270, 45) if "DRONE" in video else np.zeros((0, 4), np.float32)
            cv2.imwrite(str(root / "images" / f"{name}.jpg"), img)
            (root / "labels" / f"{name}.txt").write_text(format_yolo_labels(boxes, 320, 256))
            rows.append(f"{name},{video},{len(boxes)}")
    (root / "manifest.csv").write_text("\n".join(rows) + "\n")
    return root


class _Canned:
    """A detector that answers every frame with one box at the top left (away from the drone labels)."""

    def raw(self, rgb: np.ndarray, conf: float) -> tuple[np.ndarray, np.ndarray]:
        return _box(10, 10, 30, 30), np.asarray([0.3], np.float32)


def test_mined_sources_list_hard_frames_and_write_backgrounds(tmp_path: Path) -> None:
    real = _real_folder(tmp_path / "real")
    samples = find_samples(real, None)
    n = mine_hard(_Canned(), samples, tmp_path / "hard", conf=0.2, progress=False)  # type: ignore[arg-type]
    assert n == 6
    hard = find_samples(tmp_path / "hard", "train")  # the list trains as a source of its own
    assert sorted(s.key for s in hard) == sorted(s.key for s in samples)
    assert all(s.image_path.exists() for s in hard)
    assert write_backgrounds(samples, tmp_path / "bg") == 3  # the three drone frames
    bg = find_samples(tmp_path / "bg", None)
    assert len(bg) == 3
    assert all(s.group == "V_DRONE_001" for s in bg)
    img = cv2.imread(str(bg[0].image_path))
    assert img.shape == (256, 320, 3)
    assert abs(int(img[35, 260, 0]) - 114) <= 3  # the drone's place is grey, the rest kept
    assert bg[0].label_path is not None
    assert bg[0].label_path.read_text() == ""


def test_range_bins_report_recall_and_ap_per_two_metres() -> None:
    stats = DetectionStats()
    hit = np.asarray([0.9], np.float32)
    stats.add(_box(10, 10, 40, 40), hit, _box(10, 10, 40, 40), 3.0)
    stats.add(_box(10, 10, 40, 40), hit, _box(10, 10, 40, 40), 7.1)
    stats.add(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), _box(50, 50, 60, 60), 7.9)
    stats.add(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros((0, 4), np.float32), None)
    bins = range_bins(stats, 0.35)
    assert [b["range_m"] for b in bins] == [[2.0, 4.0], [6.0, 8.0]]
    assert bins[0]["recall"] == 1.0
    assert bins[0]["leader_boxes"] == 1
    assert bins[1]["recall"] == 0.5
    assert bins[1]["leader_boxes"] == 2
    assert bins[1]["map50"] == pytest.approx(0.5, abs=0.01)


class _WindowOnly:
    """Finds the leader only when searched in a window; records the windows it was given."""

    conf_threshold = 0.35
    input_size_px = 416

    def __init__(self) -> None:
        self.windows: list[tuple[tuple[int, int, int, int], int]] = []

    def raw(self, rgb: np.ndarray, conf: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32)

    def detect_window(
        self, rgb: np.ndarray, xywh: tuple[int, int, int, int], size: int, conf: float | None = None
    ) -> DetectorResult:
        self.windows.append((xywh, size))
        return DetectorResult([Detection((300.0, 200.0, 330.0, 220.0), 0.8)])


def test_window_evaluation_searches_the_services_window_on_each_label(tmp_path: Path) -> None:
    img = tmp_path / "f.png"
    cv2.imwrite(str(img), np.full((480, 640, 3), 120, np.uint8))
    lab = tmp_path / "f.txt"
    lab.write_text(format_yolo_labels(_box(300, 200, 330, 220), 640, 480))
    empty = tmp_path / "e.txt"
    empty.write_text("")
    samples = [Sample(img, lab, 7.0, True), Sample(img, empty, None, False)]
    det = _WindowOnly()
    stats = collect_window(det, samples, DetectorConfig(), progress=False)  # type: ignore[arg-type]
    assert len(stats.records) == 1  # the leader-free frame has no window
    ((xywh, size),) = det.windows
    assert xywh[2] == 128
    assert size == 224
    s = stats.summary(0.35)
    assert s["recall"] == 1.0
    assert range_bins(stats, 0.35)[0]["range_m"] == [6.0, 8.0]
