"""The per-frame detector: letterbox -> network (torch or ONNX Runtime) -> threshold, decode, NMS -> boxes.

:class:`FrameDetector` implements the :class:`companion.perception.types.Detector` protocol around an
:class:`Engine` (anything that maps the input array to the raw level maps). The ONNX Runtime engine lives
here and never imports torch; the torch engine is in :mod:`.torch_engine`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import RgbImage
from companion.kernel.errors import ModelError
from companion.perception.detector.letterbox import Letterboxer, boxes_to_source
from companion.perception.detector.postprocess import Decoder
from companion.perception.types import Detection, DetectorResult, DetectorTiming

log = logging.getLogger(__name__)

#: ONNX metadata key under which the export stores :class:`ModelInfo` as JSON.
ONNX_META_KEY = "wingman_detector"
#: Window letterboxes kept by :meth:`FrameDetector.detect_window` before the cache is cleared.
MAX_WINDOW_GEOMETRIES = 16


@dataclass(frozen=True, slots=True)
class ModelInfo:
    """What post-processing needs to know about a network, stored with its weights."""

    strides: tuple[int, ...]
    reg_max: int
    #: The input size the model was trained at (the config's ``input_size_px`` may differ).
    train_input_size_px: int

    def to_json(self) -> str:
        return json.dumps(
            {
                "strides": list(self.strides),
                "reg_max": self.reg_max,
                "train_input_size_px": self.train_input_size_px,
            }
        )

    @classmethod
    def from_json(cls, text: str) -> ModelInfo:
        d = json.loads(text)
        return cls(tuple(int(s) for s in d["strides"]), int(d["reg_max"]), int(d["train_input_size_px"]))


class Engine(Protocol):
    """Runs the network: (1, 3, H, W) float32 in [0, 1] -> one raw map per level, (1, C, H/s, W/s)."""

    info: ModelInfo
    name: str

    def __call__(self, images: NDArray[np.float32]) -> Sequence[NDArray[np.float32]]: ...


class OnnxEngine:
    """ONNX Runtime on the CPU (or a GPU provider when the installed onnxruntime offers one)."""

    name = "onnxruntime"

    def __init__(self, path: Path, threads: int, providers: Sequence[str] | None = None) -> None:
        import onnxruntime as ort  # noqa: PLC0415  (kept off the import path of the light modules)

        so = session_options(threads)
        try:
            self.session = ort.InferenceSession(
                str(path), so, providers=list(providers or ["CPUExecutionProvider"])
            )
        except Exception as exc:  # onnxruntime raises its own untyped errors for bad files
            raise ModelError(f"cannot load ONNX model {path}: {str(exc).splitlines()[0]}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if ONNX_META_KEY not in meta:
            raise ModelError(f"{path} is not a Wingman detector export (no '{ONNX_META_KEY}' metadata)")
        self.info = ModelInfo.from_json(meta[ONNX_META_KEY])
        self.input_name = self.session.get_inputs()[0].name
        self.providers = tuple(self.session.get_providers())

    def __call__(self, images: NDArray[np.float32]) -> Sequence[NDArray[np.float32]]:
        out: list[NDArray[np.float32]] = self.session.run(None, {self.input_name: images})
        return out


class FrameDetector:
    """A :class:`~companion.perception.types.Detector`: boxes in source-frame pixels, best first.

    Not thread-safe (it reuses its letterbox buffer); the service keeps at most one inference in flight.
    """

    def __init__(
        self,
        engine: Engine,
        input_size_px: int,
        conf_threshold: float,
        nms_iou: float,
        max_det: int = 20,
    ) -> None:
        self.engine = engine
        self.input_size_px = input_size_px
        self.conf_threshold = conf_threshold
        self.nms_iou = nms_iou
        self.max_det = max_det
        self.letterbox = Letterboxer(input_size_px)
        self._window_letterbox: dict[tuple[int, int, int], Letterboxer] = {}
        self.decoder = Decoder(engine.info.strides, engine.info.reg_max)

    @property
    def runtime(self) -> str:
        return self.engine.name

    def detect(self, rgb: RgbImage) -> DetectorResult:
        return self._run(self.letterbox, rgb, 0, 0, self.conf_threshold)

    def detect_window(
        self,
        rgb: RgbImage,
        window_xywh_px: tuple[int, int, int, int],
        input_size_px: int,
        conf_threshold: float | None = None,
    ) -> DetectorResult:
        """Detect in the window ``(x0, y0, w, h)`` (``[x0, x0 + w) x [y0, y0 + h)``) at ``input_size_px``.

        Boxes come back in frame pixels, clipped to the window; ``conf_threshold`` (default: the detector's)
        may be lower where the leader is expected. One letterbox (and its buffers) per window
        geometry, so a caller should use few distinct sizes (:mod:`.roi` rounds them).
        """
        x0_px, y0_px, w_px, h_px = window_xywh_px
        key = (w_px, h_px, input_size_px)
        lb = self._window_letterbox.get(key)
        if lb is None:
            if len(self._window_letterbox) >= MAX_WINDOW_GEOMETRIES:
                self._window_letterbox.clear()
            lb = self._window_letterbox[key] = Letterboxer(input_size_px)
        window = rgb[y0_px : y0_px + h_px, x0_px : x0_px + w_px]
        conf = self.conf_threshold if conf_threshold is None else conf_threshold
        return self._run(lb, window, x0_px, y0_px, conf)

    def _run(
        self, letterbox: Letterboxer, rgb: RgbImage, dx_px: int, dy_px: int, conf_threshold: float
    ) -> DetectorResult:
        t0 = time.perf_counter()
        images, geom = letterbox(rgb)
        t1 = time.perf_counter()
        levels = self.engine(images)
        t2 = time.perf_counter()
        boxes, scores = self.decoder(levels, conf_threshold, self.nms_iou, self.max_det)
        boxes_to_source(boxes, geom)
        if dx_px or dy_px:
            boxes[:, 0::2] += dx_px
            boxes[:, 1::2] += dy_px
        dets = [
            Detection((float(b[0]), float(b[1]), float(b[2]), float(b[3])), float(s), geom.scale)
            for b, s in zip(boxes, scores, strict=True)
        ]
        t3 = time.perf_counter()
        return DetectorResult(dets, DetectorTiming((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3))

    def raw(self, rgb: RgbImage, conf_threshold: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Boxes (N, 4) in source pixels and scores (N,) at any threshold (evaluation uses a low one)."""
        images, geom = self.letterbox(rgb)
        boxes, scores = self.decoder(self.engine(images), conf_threshold, self.nms_iou, self.max_det)
        return boxes_to_source(boxes, geom), scores


def session_options(threads: int) -> Any:
    """ONNX Runtime options for the detector: ``threads`` intra-op threads, full graph optimisation.

    No busy-waiting between runs: on a 2-core board a spinning pool steals the CPU that the pose and tracker
    stages (and the rest of the service) need right after inference; p50 is unchanged.
    """
    import onnxruntime as ort  # noqa: PLC0415  (kept off the import path of the light modules)

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so
