"""The leader detector: a compact YOLO-style network written here, its training, evaluation and runtimes.

Only the modules that need torch import it (``model``, ``loss``, ``train``, ``export``, ``torch_engine``);
loading a detector for the ONNX Runtime path (:func:`load_detector`) never does.
"""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path
from typing import Literal

from companion.config import DetectorConfig
from companion.kernel.camera import RgbdFrame
from companion.kernel.errors import ModelError
from companion.perception.detector.roi import RoiDetector, focus_box
from companion.perception.detector.roi import window_note as window_note
from companion.perception.detector.runtime import FrameDetector, OnnxEngine
from companion.perception.detector.weights import verify_model_file
from companion.perception.types import DetectorResult, DetectStage

log = logging.getLogger(__name__)

Runtime = Literal["torch", "onnx"]

#: ONNX Runtime's execution providers for a ``device`` of :func:`load_detector`, in order of preference
#: (a device not listed: every provider the installed build has, in its own order).
ONNX_PROVIDERS: dict[str, list[str]] = {
    "cpu": ["CPUExecutionProvider"],
    "cuda": ["CUDAExecutionProvider", "CPUExecutionProvider"],
    "tensorrt": ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"],
}


def model_files(cfg: DetectorConfig, root: Path | None = None) -> tuple[Path, Path]:
    """The torch weights and the ONNX export named by ``cfg.model_path`` (either may be given), resolved."""
    p = Path(cfg.model_path)
    if not p.is_absolute():
        p = (root or Path.cwd()) / p
    return p.with_suffix(".pt"), p.with_suffix(".onnx")


def choose_runtime(cfg: DetectorConfig, root: Path | None = None) -> tuple[Runtime, Path]:
    """Which runtime and file ``cfg`` selects.

    ``auto`` takes ONNX Runtime when the export exists and onnxruntime imports: on a 2-core CPU it runs this
    network 2-3x faster than torch eager (``companion bench`` shows both side by side); otherwise torch.
    """
    pt, onnx = model_files(cfg, root)
    if cfg.runtime == "torch":
        return "torch", pt
    if cfg.runtime == "onnx":
        return "onnx", onnx
    if onnx.exists() and importlib.util.find_spec("onnxruntime") is not None:
        return "onnx", onnx
    return "torch", pt


def load_detector(
    cfg: DetectorConfig, root: Path | None = None, runtime: Runtime | None = None, device: str = "cpu"
) -> FrameDetector:
    """Verify the model's checksum and build the detector ``cfg`` asks for.

    ``detector.model_sha256`` (or, when empty, the sidecar ``.sha256`` file beside the model) pins the file
    named by ``model_path``; the sibling file actually loaded (the ONNX export for the ONNX runtime) must
    match the sidecar too. Raises :class:`ModelError` with one line for a missing, corrupt or mismatched file.
    """
    chosen, path = (
        choose_runtime(cfg, root) if runtime is None else (runtime, model_files(cfg, root)[runtime == "onnx"])
    )
    named = (
        Path(cfg.model_path) if Path(cfg.model_path).is_absolute() else (root or Path.cwd()) / cfg.model_path
    )
    verify_model_file(named, cfg.model_sha256)
    if path != named:
        verify_model_file(path)
    if chosen == "onnx":
        engine: OnnxEngine | object = OnnxEngine(path, cfg.threads, ONNX_PROVIDERS.get(device))
    else:
        if importlib.util.find_spec("torch") is None:
            raise ModelError("detector.runtime 'torch' needs torch, which is not installed; use 'onnx'")
        from companion.perception.detector.torch_engine import TorchEngine  # noqa: PLC0415

        engine = TorchEngine(path, cfg.threads, device)
    log.info("detector: %s (%s), input %d px", path.name, chosen, cfg.input_size_px)
    return FrameDetector(engine, cfg.input_size_px, cfg.conf_threshold, cfg.nms_iou)  # type: ignore[arg-type]


def detect_stage(
    cfg: DetectorConfig, root: Path | None = None, runtime: Runtime | None = None, device: str = "cpu"
) -> DetectStage:
    """The service's per-frame detection: :func:`load_detector`, and a window on the tracked leader.

    The window (see :mod:`.roi`) is searched first when ``cfg.roi_enabled``.
    """
    detector = load_detector(cfg, root, runtime, device)
    if not cfg.roi_enabled:
        return DetectStage(lambda frame: detector.detect(frame.rgb), description=_describe(detector, cfg))
    roi = RoiDetector(detector, cfg)

    def detect(frame: RgbdFrame) -> DetectorResult:
        return roi.detect(frame.rgb)

    def after_track(track: object) -> None:
        roi.focus(focus_box(track))

    return DetectStage(detect, after_track, _describe(detector, cfg))


def _describe(detector: FrameDetector, cfg: DetectorConfig) -> str:
    return f"{detector.runtime} at {detector.input_size_px} px{window_note(cfg)}"
