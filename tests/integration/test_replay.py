from __future__ import annotations

import contextlib
import csv
import json
import math
import socket
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import load_config
from companion.kernel.camera import RgbdFrame
from companion.kernel.camera_wire import encode_frame
from companion.kernel.frames import R_from_quat, quat_from_euler
from companion.perception.record import FolderRecorder
from companion.perception.transform import CameraGeometry
from tests.synthetic import frame_from_view, leader_path_cam, render, sequence_frames

N = 40


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rec") / "seq"
    with FolderRecorder(out) as rec:
        for frame in sequence_frames(N):
            rec.write(frame)
    return out


def rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_replay_writes_estimates_and_errors(
    recording: Path,
    tmp_path: Path,
    repo_root: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("WINGMAN_LEADER__BOX_CENTRE_BELOW_M", "0.0")  # the synthetic quad has no legs
    out, js = tmp_path / "est.csv", tmp_path / "sum.json"
    cfg = str(repo_root / "config/wingman.toml")
    rc = main(["replay", "--config", cfg, "--source", f"file:{recording}", "--detector", "truth",
               "--out", str(out), "--json", str(js)])  # fmt: skip
    assert rc == 0
    table = capsys.readouterr().out
    assert "rmse m" in table
    assert "pose+track ms" in table
    got = rows(out)
    assert len(got) == N
    assert [r["status"] for r in got[:3]] == ["tentative", "tentative", "confirmed"]
    summary = json.loads(js.read_text())
    assert summary["frames"] == N
    assert summary["frames_usable"] >= N - 2
    # The summary counts what the CSV says: every confirmed or coasting row is a tracked frame.
    tracked = sum(r["status"] in ("confirmed", "coasting") for r in got)
    assert summary["frames_tracked"] == tracked
    assert f"tracked {tracked} (confirmed or coasting)" in table
    # Synthetic D435 noise, truthful boxes with 1 px jitter: well inside the bars.
    assert summary["bands"][0]["rmse_m"] < 0.10
    assert summary["bearing_rmse_deg"] < 0.5
    # ...and better than the paper's centre-patch depth on the same boxes.
    assert summary["bands"][0]["rmse_m"] < summary["bands"][0]["paper_method_rmse_m"]


def test_record_then_replay_round_trips(recording: Path, tmp_path: Path, repo_root: Path) -> None:
    cfg = str(repo_root / "config/wingman.toml")
    copy = tmp_path / "copy"
    assert main(["record", "--config", cfg, "--source", f"file:{recording}", "--out", str(copy)]) == 0
    bag = tmp_path / "copy.bag"
    assert main(["record", "--config", cfg, "--source", f"file:{recording}", "--out", str(bag)]) == 0
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for src, out in ((recording, a), (copy, b)):
        assert main(["replay", "--config", cfg, "--source", f"file:{src}", "--detector", "truth",
                     "--out", str(out)]) == 0  # fmt: skip
    ra, rb = rows(a), rows(b)
    assert len(ra) == len(rb) == N
    for x, y in zip(ra, rb, strict=True):
        del x["det_ms"], x["pose_ms"], x["track_ms"], y["det_ms"], y["pose_ms"], y["track_ms"]
        assert x == y  # the same frames, stamps, truth and estimates, to the last digit
    # The bag has no ground truth: replaying it runs (no errors to compute) over the same frames.
    c = tmp_path / "c.csv"
    assert (
        main(["replay", "--config", cfg, "--source", f"file:{bag}", "--detector", "truth", "--out", str(c)])
        == 0
    )
    assert [r["seq"] for r in rows(c)] == [r["seq"] for r in ra]


def test_record_reports_the_frames_its_source_skipped(
    tmp_path: Path, repo_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gappy = tmp_path / "gappy"
    frames = sequence_frames(8)
    with FolderRecorder(gappy) as rec:
        for frame in frames[:3] + frames[5:]:  # frames 3 and 4 never reached the recorder
            rec.write(frame)
    copy = tmp_path / "copy"
    cfg = str(repo_root / "config/wingman.toml")
    assert main(["record", "--config", cfg, "--source", f"file:{gappy}", "--out", str(copy)]) == 0
    gap_s = frames[5].stamp_s - frames[2].stamp_s

    def said(out: Path) -> str:
        return (
            f"recorded 6 frames to {out}; the source skipped 2 (gaps in its frame numbers, longest "
            f"{gap_s:.2f} s): the camera dropped them before they were read"
        )

    assert capsys.readouterr().err.strip().splitlines()[-1] == said(copy)
    # The copy keeps the source's frame numbers, so a second copy reports the same gap.
    again = tmp_path / "again"
    assert main(["record", "--config", cfg, "--source", f"file:{copy}", "--out", str(again)]) == 0
    assert capsys.readouterr().err.strip().splitlines()[-1] == said(again)


def _strict_json(text: str) -> object:
    def no_constant(name: str) -> object:
        raise AssertionError(f"{name} is not JSON")

    return json.loads(text, parse_constant=no_constant)


def test_truth_without_the_leader_in_view_is_counted_as_truth(
    tmp_path: Path, repo_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Truth records whose box is null (the leader out of view): truth all the same, and JSON with nulls."""
    rec = tmp_path / "away"
    with FolderRecorder(rec) as r:
        for frame in sequence_frames(12):
            assert frame.truth is not None
            r.write(replace(frame, truth=replace(frame.truth, box_xyxy_px=None, visible_fraction=0.0)))
    js = tmp_path / "sum.json"
    cfg = str(repo_root / "config/wingman.toml")
    rc = main(
        ["replay", "--config", cfg, "--source", f"file:{rec}", "--detector", "truth", "--json", str(js)]
    )
    out = capsys.readouterr().out.splitlines()
    assert rc == 0
    assert out[0] == (
        "frames 12, tracked 0 (confirmed or coasting), with ground truth 12 (the leader in view in 0), "
        "tracked with the leader in view 0"
    )
    assert out[1] == "the ground truth has the leader in view in no frame: no errors to compute"
    summary = _strict_json(js.read_text())
    assert isinstance(summary, dict)
    assert summary["frames_with_truth"] == 12
    assert summary["frames_leader_in_view"] == 0
    assert summary["coverage"] is None
    assert summary["rmse_m"] is None


@contextlib.contextmanager
def camera_server(sock_path: Path, frames: list[RgbdFrame], connections: int = 1) -> Iterator[None]:
    """The simulator's camera server as the wire sees it: ``frames`` to each client, and never an end."""
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock_path))
    server.listen(connections)
    done = threading.Event()

    def serve() -> None:
        for _ in range(connections):
            conn, _ = server.accept()
            with conn:
                try:
                    for frame in frames:
                        for part in encode_frame(frame):
                            conn.sendall(part)
                except OSError:
                    continue  # the reader went away
                done.wait(0.5)

    thread = threading.Thread(target=serve, name="test-camera-server", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join(5)
        server.close()


def test_replay_of_a_live_source_stops_after_frames(
    tmp_path: Path, repo_root: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--source sim`` against a camera socket that never ends: ``--frames`` ends the replay."""
    sock_path = tmp_path / "cam.sock"
    monkeypatch.setenv("WINGMAN_CAMERA__PATH", str(sock_path))
    monkeypatch.setenv("WINGMAN_LEADER__BOX_CENTRE_BELOW_M", "0.0")
    with camera_server(sock_path, sequence_frames(40)):
        cfg = str(repo_root / "config/wingman.toml")
        rc = main(["replay", "--config", cfg, "--source", "sim", "--frames", "12", "--detector", "truth"])
    assert rc == 0
    assert capsys.readouterr().out.splitlines()[0].startswith("frames 12, ")


def _flown(n: int, repo_root: Path) -> list[RgbdFrame]:
    """``n`` frames of a leader on a smooth path (NED, relative) seen by a follower that pitches, rolls and
    yaws as a follower holding formation does; the follower's attitude is in each frame's ground truth."""
    geom = CameraGeometry.from_mount(load_config(repo_root / "config/wingman.toml").camera.mount)
    rng = np.random.default_rng(0)
    eye = np.eye(3)
    frames = []
    for k in range(n):
        t = k / 30.0
        q = quat_from_euler(0.08 * math.sin(2.1 * t), 0.12 * math.sin(2.7 * t), 0.1 * math.sin(1.3 * t))
        p_ned_rel = geom.cam_to_ned_rel(leader_path_cam(t), eye)
        p_cam = geom.ned_rel_to_cam(p_ned_rel, R_from_quat(q))
        f = frame_from_view(render(p_cam, rng=rng, hole_fraction=0.03), 50.0 + t, seq=k)
        assert f.truth is not None
        frames.append(replace(f, truth=replace(f.truth, q_ned_follower_wxyz=q)))
    return frames


def test_a_live_source_scores_as_its_recording_does(
    tmp_path: Path, repo_root: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same flight replayed live (``--source sim``) and recorded then replayed: the same figures.

    The live frames carry the follower's attitude in their ground truth, as a recording of them keeps it;
    the tracker works in NED, so a replay that left it out scored the follower's turns as tracker error.
    """
    n = 60
    frames = _flown(n, repo_root)
    sock_path = tmp_path / "cam.sock"
    monkeypatch.setenv("WINGMAN_CAMERA__PATH", str(sock_path))
    monkeypatch.setenv("WINGMAN_LEADER__BOX_CENTRE_BELOW_M", "0.0")
    cfg = str(repo_root / "config/wingman.toml")
    live_js, rec_js, level_js = tmp_path / "live.json", tmp_path / "rec.json", tmp_path / "level.json"
    rec = tmp_path / "rec"
    with camera_server(sock_path, frames, connections=2):
        assert main(["replay", "--config", cfg, "--source", "sim", "--frames", str(n), "--detector", "truth",
                     "--json", str(live_js)]) == 0  # fmt: skip
        assert (
            main(["record", "--config", cfg, "--source", "sim", "--frames", str(n), "--out", str(rec)]) == 0
        )
    assert main(["replay", "--config", cfg, "--source", f"file:{rec}", "--detector", "truth",
                 "--json", str(rec_js)]) == 0  # fmt: skip
    live, recorded = json.loads(live_js.read_text()), json.loads(rec_js.read_text())
    assert live.pop("attitude") == "ground truth"
    assert recorded.pop("attitude") == "recording"
    for summary in (live, recorded):
        del summary["stage_ms_p50"], summary["stage_ms_p95"]
    assert live == recorded  # to the last digit
    assert live["frames_usable"] >= n - 3
    # Without the attitude (a camera with no telemetry) the follower's tilts and turns count as tracker
    # error, and the summary says so.
    level = tmp_path / "level"
    with FolderRecorder(level) as r:
        for f in frames:
            assert f.truth is not None
            r.write(replace(f, truth=replace(f.truth, q_ned_follower_wxyz=None)))
    capsys.readouterr()
    assert main(["replay", "--config", cfg, "--source", f"file:{level}", "--detector", "truth",
                 "--json", str(level_js)]) == 0  # fmt: skip
    assert "the tracker assumed the follower level and never turning" in capsys.readouterr().out
    assert json.loads(level_js.read_text())["rmse_m"] > 1.5 * live["rmse_m"]


def test_replay_help_names_every_source() -> None:
    from companion.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    text = sub.choices["replay"].format_help()  # type: ignore[attr-defined]
    assert "file:PATH" in text
    assert "sim" in text
    assert "realsense" in text
    assert "--frames" in text
