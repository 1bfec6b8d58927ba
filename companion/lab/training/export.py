"""ONNX export (opset >= 17) of shipped weights, with the metadata the ONNX Runtime path needs (torch).

The exported graph is the network with BatchNorm folded: input ``images`` (1, 3, H, W) float32 in [0, 1],
H and W any multiple of 32; one output per level (``p8``, ``p16``, ``p32``). Decoding and NMS stay in numpy
(:mod:`.postprocess`), shared with the torch path.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import torch

from companion.perception.detector.runtime import ONNX_META_KEY, OnnxEngine
from companion.perception.detector.torch_engine import TorchEngine, load_weights, model_info
from companion.perception.detector.weights import sha256_file, sidecar_path, write_sidecar

MIN_OPSET = 17


def export_onnx(weights: Path, out: Path, opset: int = MIN_OPSET) -> Path:
    """Export ``weights`` (a shipped ``.pt``) to ``out``; returns ``out``."""
    import onnx  # noqa: PLC0415

    if opset < MIN_OPSET:
        raise ValueError(f"opset {opset} < {MIN_OPSET}")
    net, size, _ = load_weights(weights)
    net = net.fuse().eval()
    info = model_info(net, size)
    dummy = torch.zeros(1, 3, 256, 320)
    names = [f"p{s}" for s in info.strides]
    axes = {"images": {2: "height", 3: "width"}} | {n: {2: f"h{n}", 3: f"w{n}"} for n in names}
    buf = io.BytesIO()  # the legacy exporter writes to any binary file object despite its annotation
    with warnings.catch_warnings():
        warnings.simplefilter(
            "ignore"
        )  # the legacy exporter's deprecation notice; dynamo=True needs onnxscript
        torch.onnx.export(
            net,
            (dummy,),
            buf,  # type: ignore[arg-type]
            opset_version=opset,
            dynamo=False,
            input_names=["images"],
            output_names=names,
            dynamic_axes=axes,
            do_constant_folding=True,
        )
    model = onnx.load_from_string(buf.getvalue())
    meta = model.metadata_props.add()
    meta.key, meta.value = ONNX_META_KEY, info.to_json()
    src = model.metadata_props.add()
    src.key, src.value = "source_weights_sha256", sha256_file(weights)
    model.producer_name = "wingman"
    onnx.checker.check_model(model)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out))
    return out


def max_output_difference(weights: Path, onnx_path: Path, images: list[np.ndarray]) -> float:
    """Largest absolute difference between torch and ONNX Runtime raw outputs over ``images`` (1,3,H,W)."""
    t = TorchEngine(weights, threads=2)
    o = OnnxEngine(onnx_path, threads=2)
    worst = 0.0
    for x in images:
        for a, b in zip(t(x), o(x), strict=True):
            worst = max(worst, float(np.abs(a - b).max()))
    return worst


def export_and_sign(weights: Path, out: Path | None = None, opset: int = MIN_OPSET) -> tuple[Path, Path]:
    """Export (beside the weights by default), rewrite the sidecar with both checksums; (onnx, sidecar)."""
    onnx_path = export_onnx(weights, out or weights.with_suffix(".onnx"), opset)
    side = sidecar_path(weights)
    if onnx_path.parent == weights.parent and onnx_path.stem == weights.stem:
        write_sidecar(side, [weights, onnx_path])
    return onnx_path, side
