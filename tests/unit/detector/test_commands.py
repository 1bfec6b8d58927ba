from __future__ import annotations

import json
from pathlib import Path

import pytest

from companion.cli import main
from companion.lab.bench import NOT_MEASURED, percentiles_ms, run_bench, synthetic_frames


def test_eval_command_writes_every_figure(
    tiny_dataset: Path, shipped_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "eval.json"
    code = main(["detector", "eval", "--data", str(tiny_dataset), "--model", str(shipped_model),
                 "--json", str(out), "--no-progress"])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "[test]" in text
    assert "mAP@0.5" in text
    assert "leader-free" in text
    s = json.loads(out.read_text())
    assert s["split"] == "test"
    assert s["images"] == 10
    for key in ("precision", "recall", "map50", "map50_95", "recall_by_range_m", "leader_free_fp_rate"):
        assert key in s
    assert set(s["recall_by_range_m"]) == {"0-5", "5-10", "10-15", "15-20"}


def test_eval_of_a_flat_folder_without_ranges(
    tiny_dataset: Path, shipped_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flat = tmp_path / "flat"
    flat.mkdir()
    (flat / "images").symlink_to(tiny_dataset / "images" / "val")
    (flat / "labels").symlink_to(tiny_dataset / "labels" / "val")
    assert (
        main(["detector", "eval", "--data", str(flat), "--model", str(shipped_model), "--no-progress"]) == 0
    )
    assert "no ranges known" in capsys.readouterr().out


def test_eval_missing_folder_is_a_usage_error(shipped_model: Path, tmp_path: Path) -> None:
    assert main(["detector", "eval", "--data", str(tmp_path / "none"), "--model", str(shipped_model)]) == 2


def test_bench_reports_every_stage_for_both_runtimes(shipped_model: Path) -> None:
    from companion.commands.bench import pose_filter_stages
    from companion.config import Config
    from companion.perception.detector import load_detector

    cfg = Config().model_copy(
        update={"detector": Config().detector.model_copy(update={"model_path": str(shipped_model)})}
    )
    dets = {"torch-cpu": load_detector(cfg.detector, runtime="torch"),
            "onnxruntime-cpu": load_detector(cfg.detector, runtime="onnx")}  # fmt: skip
    result = run_bench(cfg, dets, synthetic_frames(4), warmup=1, pose_filter=pose_filter_stages)
    assert result["frame_size_px"] == [640, 480]
    for name in dets:
        stages = result["runtimes"][name]
        for stage in ("decode", "preprocess", "inference", "postprocess", "pose", "filter", "total"):
            v = stages[stage]
            assert v == NOT_MEASURED or (v["n"] == 4 and v["p50_ms"] <= v["p95_ms"] <= v["p99_ms"])
        assert isinstance(stages["inference"], dict)
        assert isinstance(stages["pose"], dict)
        assert isinstance(stages["filter"], dict)


def test_percentiles() -> None:
    p = percentiles_ms([float(i) for i in range(1, 101)])
    assert p["p50_ms"] == pytest.approx(50.5)
    assert p["p99_ms"] == pytest.approx(99.01)
    assert p["n"] == 100


def test_manifest_facts_reach_the_samples(tmp_path: Path) -> None:
    from companion.perception.detector.dataset import find_samples

    (tmp_path / "images" / "test").mkdir(parents=True)
    for n in ("a", "b", "c"):
        (tmp_path / "images" / "test" / f"{n}.jpg").write_bytes(b"")
    (tmp_path / "manifest.csv").write_text(
        "image,split,has_leader,range_m,visible_fraction\n"
        "images/test/a.jpg,test,1,7.5,0.4\nimages/test/b.jpg,test,0,,\nimages/test/d.jpg,test,1,9.0,0.000\n"
    )
    (tmp_path / "images" / "test" / "d.jpg").write_bytes(b"")
    s = {x.key: x for x in find_samples(tmp_path, "test")}
    assert (s["a"].range_m, s["a"].leader_visible) == (7.5, True)
    assert (s["b"].range_m, s["b"].leader_visible) == (None, False)
    assert (s["d"].range_m, s["d"].leader_visible) == (9.0, False)  # in the scene, out of view
    assert (s["c"].range_m, s["c"].leader_visible, s["c"].label_path) == (None, None, None)


def test_bench_names_each_gpu_runtime_or_why_it_is_absent(monkeypatch: pytest.MonkeyPatch) -> None:
    import onnxruntime as ort
    import torch

    from companion.lab.bench import format_bench, gpu_runtimes

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    absent = gpu_runtimes()
    assert absent["torch-cuda"] == "absent: torch sees no CUDA device"
    assert absent["onnxruntime-cuda"].startswith("absent: ")
    assert absent["onnxruntime-tensorrt"].startswith("absent: ")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda _=0: "Some GPU")
    monkeypatch.setattr(
        ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"]
    )
    present = gpu_runtimes()
    assert present == {
        "torch-cuda": "Some GPU",
        "onnxruntime-cuda": "present",
        "onnxruntime-tensorrt": "absent: this onnxruntime build has no TensorrtExecutionProvider",
    }
    result = {
        "frames": 1,
        "frame_size_px": [640, 480],
        "input_size_px": 416,
        "threads": 2,
        "machine": "x",
        "load_average_1_5_15": None,
        "total_covers": ["preprocess"],
        "runtimes": {},
        "gpu": {
            "runtimes": absent,
            "torch_cuda_network": {
                "device": "Some GPU",
                "input_shape": [1, 3, 320, 416],
                "network": percentiles_ms([3.0, 3.1, 2.9]),
            },
        },
    }
    text = format_bench(result)
    assert "onnxruntime-tensorrt: absent" in text
    assert "network alone on Some GPU (torch, CUDA events, input 320x416): p50 3.000" in text
