"""Shipped weights as torch files, and the torch inference engine (imports torch).

The weights file is a plain ``torch.save`` dict (loaded with ``weights_only=True``: tensors and plain
containers only, no pickled code): format tag, architecture name (``arch``; a file without one holds a
:class:`LeaderNet`), its spec, training input size, state dict, and free-form metadata (data recipe, seed,
command) for the model card.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from companion.kernel.errors import ModelError
from companion.perception.detector.model import ARCH_LEADERNET, DetectorNet, build_net
from companion.perception.detector.runtime import ModelInfo

WEIGHTS_FORMAT = "wingman-leader-detector/1"


def model_info(net: DetectorNet, train_input_size_px: int) -> ModelInfo:
    """What post-processing needs from a network."""
    return ModelInfo(net.spec.strides, net.spec.reg_max, train_input_size_px)


def save_weights(path: Path, net: DetectorNet, train_input_size_px: int, meta: dict[str, Any]) -> None:
    """Write shippable weights (fp32 state dict, unfused) with the spec and metadata."""
    state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "format": WEIGHTS_FORMAT,
            "arch": net.arch,
            "spec": net.spec.to_dict(),
            "train_input_size_px": train_input_size_px,
            "state_dict": state,
            "meta": meta,
        },
        path,
    )


def load_weights(path: Path, device: str = "cpu") -> tuple[DetectorNet, int, dict[str, Any]]:
    """Build the network from a weights file; returns it (eval mode), its training input size and metadata."""
    try:
        blob = torch.load(path, map_location=device, weights_only=True)
    except FileNotFoundError:
        raise ModelError(f"model file not found: {path}") from None
    except Exception as exc:  # torch raises several unrelated types for a damaged file
        raise ModelError(f"cannot load weights {path}: {str(exc).splitlines()[0][:160]}") from None
    if not isinstance(blob, dict) or blob.get("format") != WEIGHTS_FORMAT:
        raise ModelError(f"{path} is not a Wingman detector weights file ({WEIGHTS_FORMAT})")
    try:
        net = build_net(str(blob.get("arch", ARCH_LEADERNET)), blob["spec"])
    except (ValueError, TypeError, KeyError) as exc:
        raise ModelError(f"{path}: {exc}") from None
    try:
        net.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise ModelError(
            f"{path}: weights do not fit the network: {str(exc).splitlines()[0][:160]}"
        ) from None
    return net.to(device).eval(), int(blob["train_input_size_px"]), dict(blob.get("meta", {}))


class TorchEngine:
    """Eager torch inference with BatchNorm folded, on the CPU (``threads``) or a CUDA device."""

    def __init__(self, path: Path, threads: int, device: str = "cpu") -> None:
        if device == "cpu":
            torch.set_num_threads(threads)
        net, size, self.meta = load_weights(path, device)
        self.net = net.fuse().eval()
        self.device = torch.device(device)
        self.info = model_info(net, size)
        self.name = "torch" if device == "cpu" else f"torch-{device}"

    @torch.inference_mode()
    def __call__(self, images: NDArray[np.float32]) -> Sequence[NDArray[np.float32]]:
        x = torch.from_numpy(images).to(self.device, non_blocking=True)
        return [o.float().cpu().numpy() for o in self.net(x)]
