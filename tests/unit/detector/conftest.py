"""Fixtures shared by the detector tests: a tiny synthetic dataset and a small shipped-format model."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from tests.unit.detector.synthetic import make_dataset

# The modules that import torch when they load. Where torch is not installed (the SITL test image: the service
# runs the detector's ONNX export) they are left out, not reported as collection errors.
collect_ignore = (
    []
    if importlib.util.find_spec("torch") is not None
    else [
        "test_augment.py",
        "test_detector_backbone.py",
        "test_detector_mixing.py",
        "test_finetune.py",
        "test_model_loss.py",
        "test_range_recipe.py",
        "test_runtime.py",
        "test_train.py",
    ]
)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tiny_dataset")
    return make_dataset(root, {"train": 24, "val": 8, "test": 10}, seed=3, size=(160, 120))


@pytest.fixture(scope="session")
def shipped_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A randomly initialised default-spec model saved as models/leader_detector.{pt,onnx,sha256}."""
    import torch

    from companion.lab.training.export import export_and_sign
    from companion.perception.detector.leadernet import LeaderNet
    from companion.perception.detector.torch_engine import save_weights

    torch.manual_seed(0)
    net = LeaderNet()
    # Non-trivial BatchNorm statistics, so that folding them into the convs is really exercised.
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                assert m.running_mean is not None
                assert m.running_var is not None
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
        for head in net.heads:
            # Widely spread scores and small, barely overlapping boxes (about two strides wide), so that the
            # two runtimes' detections are comparable one to one (no near-ties for NMS or max_det to break).
            head.cls[-1].weight.normal_(0.0, 3.0)
            head.cls[-1].bias.fill_(-3.0)
            head.box[-1].weight.normal_(0.0, 0.05)
            head.box[-1].bias.copy_(-4.0 * (torch.arange(16.0) - 1.0).abs().repeat(4))
    folder = tmp_path_factory.mktemp("models")
    pt = folder / "leader_detector.pt"
    save_weights(pt, net, 320, {"note": "random init, tests only"})
    export_and_sign(pt)
    return pt
