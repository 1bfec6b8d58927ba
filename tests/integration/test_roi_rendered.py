"""The shipped detector on rendered frames: a window on the leader finds it where the whole frame does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import DetectorConfig
from companion.lab.evaluation.scoring import DETECTED_IOU, iou
from companion.perception.detector import load_detector
from companion.perception.detector.roi import RoiDetector
from tests.render_sequences import frames

pytestmark = pytest.mark.render


def test_window_recall_beyond_5_m_on_rendered_frames(repo_root: Path) -> None:
    cfg = DetectorConfig(model_path=str(repo_root / "models" / "leader_detector.pt"))
    det = load_detector(cfg)
    roi = RoiDetector(det, cfg)
    whole_hits, window_hits = [], []
    for f in frames("weave", 12.0, seed=5, fps=2.5):  # leader 3 -> 12 m ahead, weaving
        assert f.truth is not None
        assert f.truth.box_xyxy_px is not None
        box = f.truth.box_xyxy_px
        if float(np.linalg.norm(f.truth.p_cam_leader_m)) < 5.0:
            continue
        whole_hits.append(any(iou(d.box_xyxy_px, box) >= DETECTED_IOU for d in det.detect(f.rgb).detections))
        roi.reset()
        roi.focus(box)  # as if the tracker had accepted the leader's box in the frame before
        window_hits.append(any(iou(d.box_xyxy_px, box) >= DETECTED_IOU for d in roi.detect(f.rgb).detections))
    assert len(window_hits) >= 15
    assert np.mean(window_hits) >= 0.9  # measured 1.0 (whole frame: 0.5) with the epoch-18 weights
    assert np.mean(window_hits) >= np.mean(whole_hits)
    assert roi.window_frames == len(window_hits)
