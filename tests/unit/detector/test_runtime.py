from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.config import DetectorConfig
from companion.kernel.errors import ModelError
from companion.lab.training.export import max_output_difference
from companion.perception.detector import choose_runtime, load_detector
from companion.perception.detector.letterbox import Letterboxer


def _cfg(model: Path, **kw: object) -> DetectorConfig:
    return DetectorConfig(model_path=str(model), **kw)  # type: ignore[arg-type]


def _frames(n: int, h: int = 480) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (h, 640, 3), dtype=np.uint8) for _ in range(n)]


def test_onnx_matches_torch_raw_outputs(shipped_model: Path) -> None:
    lb = Letterboxer(320)
    images = [lb(f)[0].copy() for f in _frames(2)]
    images.append(np.random.default_rng(1).random((1, 3, 416, 416), dtype=np.float32))  # another input size
    assert max_output_difference(shipped_model, shipped_model.with_suffix(".onnx"), images) < 2e-3


def test_both_runtimes_run_the_detector_protocol(shipped_model: Path) -> None:
    for runtime, name in (("torch", "torch"), ("onnx", "onnxruntime")):
        det = load_detector(_cfg(shipped_model, conf_threshold=0.002), runtime=runtime)  # type: ignore[arg-type]
        assert det.runtime == name
        result = det.detect(_frames(1)[0])
        assert result.timing is not None
        assert result.timing.inference_ms > 0
        assert 0 < len(result.detections) <= det.max_det
        scores = [d.score for d in result.detections]
        assert scores == sorted(scores, reverse=True)
        for d in result.detections:
            x0, y0, x1, y1 = d.box_xyxy_px
            assert 0 <= x0 <= x1 <= 640
            assert 0 <= y0 <= y1 <= 480


def test_shipped_model_gives_the_same_boxes_on_both_runtimes(repo_root: Path, tmp_path: Path) -> None:
    # The raw-output test above covers any network; on the trained model, compare the final boxes too.
    from tests.unit.detector.synthetic import make_dataset

    pt = repo_root / "models" / "leader_detector.pt"
    if not pt.exists():
        pytest.skip("no shipped model in models/ yet")
    data = make_dataset(tmp_path, {"test": 6}, seed=11, size=(640, 480), empty_fraction=0.0)
    # A low threshold: the synthetic drones are crude, and the comparison needs boxes to compare.
    dets = [load_detector(_cfg(pt, conf_threshold=0.05), runtime=r) for r in ("torch", "onnx")]  # type: ignore[arg-type]
    found = 0
    for img in sorted((data / "images" / "test").glob("*.png")):
        rgb = np.ascontiguousarray(cv2.imread(str(img))[..., ::-1])
        a, b = (d.detect(rgb).detections for d in dets)
        assert len(a) == len(b)
        for da, db in zip(a, b, strict=True):
            np.testing.assert_allclose(da.box_xyxy_px, db.box_xyxy_px, atol=0.1)
            assert abs(da.score - db.score) < 2e-3
        found += len(a)
    assert found > 0


def test_auto_prefers_onnx_when_exported(shipped_model: Path, tmp_path: Path) -> None:
    assert choose_runtime(_cfg(shipped_model)) == ("onnx", shipped_model.with_suffix(".onnx"))
    lone = tmp_path / "lone.pt"
    shutil.copy(shipped_model, lone)
    assert choose_runtime(_cfg(lone)) == ("torch", lone)


def test_corrupt_or_mismatched_model_is_refused(shipped_model: Path, tmp_path: Path) -> None:
    for suffix in (".pt", ".onnx", ".sha256"):
        shutil.copy(shipped_model.with_suffix(suffix), tmp_path / f"m{suffix}")
    (tmp_path / "m.sha256").write_text((tmp_path / "m.sha256").read_text().replace("leader_detector", "m"))
    load_detector(_cfg(tmp_path / "m.pt"))  # intact: loads
    data = bytearray((tmp_path / "m.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "m.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelError, match="does not match its checksum") as exc:
        load_detector(_cfg(tmp_path / "m.pt"))
    assert "\n" not in str(exc.value)
    with pytest.raises(ModelError, match=r"detector\.model_sha256 says"):
        load_detector(_cfg(tmp_path / "m.pt", model_sha256="ab" * 32), runtime="torch")
    with pytest.raises(ModelError, match="model file not found"):
        load_detector(_cfg(tmp_path / "absent.pt"))


def test_onnx_path_does_not_import_torch(shipped_model: Path, repo_root: Path) -> None:
    code = (
        "import sys, numpy as np\n"
        "from companion.config import DetectorConfig\n"
        "from companion.perception.detector import load_detector\n"
        f"d = load_detector(DetectorConfig(model_path={str(shipped_model)!r}))\n"
        "d.detect(np.zeros((480, 640, 3), np.uint8))\n"
        "print(d.runtime, 'torch' in sys.modules)\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=repo_root, capture_output=True, text=True, timeout=60, check=False
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["onnxruntime", "False"]
