"""A simulator run's MCAP log: every channel with a schema, the run's whole duration, and replay through it.

One lockstep ``gps-loss`` run with the shipped detector, its images logged losslessly at every frame
(``viz.log_image_rate_hz = 0``, ``viz.log_image_format = "png"``): the service's recorder wrote it, the
``mcap`` library reads it, and ``companion replay``'s perception run over it finds what the run found.
"""

from __future__ import annotations

import asyncio
import json
import tomllib
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from companion.lab.evaluation.campaign import RunSpec, run_one
from companion.lab.evaluation.runlog import SIM_EPOCH_S
from companion.lab.evaluation.setup import load_detect, service_config
from companion.lab.replay import run_replay
from companion.perception.types import DetectorResult, DetectStage
from companion.viz.channels import TOPICS

pytestmark = [pytest.mark.lab, pytest.mark.slow]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("gps-loss")
    spec = RunSpec(
        "gps-loss",
        1,
        out,
        harness="lockstep",
        duration_s=2.0,
        plots=False,
        overrides=("viz.log_image_rate_hz=0", 'viz.log_image_format="png"'),
    )
    run_one(spec)
    return out


def test_every_channel_has_a_schema_and_the_log_spans_the_run(run_dir: Path) -> None:
    report = json.loads((run_dir / "report.json").read_text())
    with (run_dir / "flight.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == set(TOPICS)
    for c in topics.values():
        schema = summary.schemas[c.schema_id]
        assert schema.name == TOPICS[c.topic].schema_name
        assert schema.data  # Foxglove's protobuf descriptors or our JSON Schemas
    assert summary.schemas[topics["/camera/image"].schema_id].name == "foxglove.CompressedImage"
    start_s = summary.statistics.message_start_time / 1e9 - SIM_EPOCH_S
    end_s = summary.statistics.message_end_time / 1e9 - SIM_EPOCH_S
    assert 0.0 <= start_s < 0.1  # sim time from the fixed date: the first control step
    assert end_s == pytest.approx(report["sim_duration_s"], abs=0.1)
    counts = summary.statistics.channel_message_counts
    frames = counts[topics["/perception/frame"].id]
    assert counts[topics["/camera/image"].id] == frames  # every frame's image (rate 0)
    assert counts[topics["/mission/log"].id] >= 4  # take-off to follow, each transition once


def test_replay_of_the_log_finds_the_detections_of_the_run(run_dir: Path) -> None:
    scenario = tomllib.loads((run_dir / "scenario.toml").read_text())
    cfg = service_config(scenario.get("companion", {}))
    stage = load_detect(cfg, "network")
    replayed: dict[int, list[Any]] = {}

    def detect(frame: Any) -> DetectorResult:
        result = stage.detect(frame)
        replayed[frame.seq] = [(list(d.box_xyxy_px), d.score) for d in result.detections]
        return result

    asyncio.run(run_replay(cfg, f"file:{run_dir / 'flight.mcap'}", DetectStage(detect, stage.after_track)))
    live: dict[int, list[Any]] = {}
    with (run_dir / "flight.mcap").open("rb") as f:
        for _, _, m in make_reader(f).iter_messages(topics=["/perception/frame"]):
            rec = json.loads(m.data)
            live[rec["seq"]] = [(d["box_xyxy_px"], d["score"]) for d in rec["detections"]]
    assert len(live) > 20
    assert sum(1 for boxes in live.values() if boxes) > 10  # the leader was found in flight
    assert replayed == live


LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"


def _layout_strings(node: Any) -> list[str]:
    if isinstance(node, dict):
        return [s for v in node.values() for s in _layout_strings(v)]
    if isinstance(node, list):
        return [s for v in node for s in _layout_strings(v)]
    return [node] if isinstance(node, str) and node.startswith("/") else []


def test_the_shipped_layout_reads_what_a_run_logs(run_dir: Path) -> None:
    """Every topic and message path of docs/foxglove-layout.json resolves in a real run's log."""
    refs = _layout_strings(json.loads(LAYOUT.read_text()))
    assert len(refs) > 10
    #: For each JSON topic and field: the shortest list it held (-1: not a list), over non-null values.
    seen: dict[str, dict[str, int]] = {}
    with (run_dir / "flight.mcap").open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        for _schema, channel, message in reader.iter_messages():
            if channel.message_encoding != "json":
                continue
            fields = seen.setdefault(channel.topic, {})
            for k, v in json.loads(message.data).items():
                if v is not None:
                    n = len(v) if isinstance(v, list) else -1
                    fields[k] = min(fields.get(k, n), n)
    for ref in refs:
        topic, _, path = ref.partition(".")
        assert topic in topics, f"{ref}: no channel {topic} in the log"
        if not path:
            continue
        field, _, index = path.partition("[")
        fields = seen.get(topic, {})
        assert field in fields, f"{ref}: no message on {topic} has {field} ({sorted(fields)})"
        if index:
            assert fields[field] > int(index.rstrip("]")), f"{ref}: {field} is shorter"
