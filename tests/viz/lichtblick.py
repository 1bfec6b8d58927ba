"""TEST TOOL: a flight in Lichtblick (the open fork of Foxglove Studio) in headless Chromium, as seen.

It serves the app's static web build with its own ``serve.py`` (HTTP Range, which an MCAP opened by URL
needs), opens a flight's MCAP (``?ds=remote-file``) or a live view (``?ds=foxglove-websocket``) with the
shipped layout (docs/foxglove-layout.json), takes screenshots and reads what a person would see: each
panel's pixels (found by the app's own panel ids, ``Image!camera``, ``3D!scene``, ...) and the Alerts tab.

Where things are: the app folder is ``LICHTBLICK_WEB`` (default ``../shared/lichtblick-web`` beside
the repository); Chromium is ``LICHTBLICK_CHROMIUM`` (default ``chromium`` on PATH, Debian's package), driven
by the ``playwright`` package with no browser of its own.

The screenshots in docs/visualisation.md come from here::

    python -m tests.viz.lichtblick log FLIGHT.mcap OUT.png [--cut 33 37] [--play 3]
    python -m tests.viz.lichtblick cut FLIGHT.mcap CUT.mcap 33 37
    python -m tests.viz.lichtblick fixture      # the log the tests open, flown again and cut
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
LAYOUT = REPO / "docs" / "foxglove-layout.json"
#: Sim time zero of a simulator run's log (companion.lab.evaluation.runlog.SIM_EPOCH_S): 2000-01-01 UTC.
SIM_EPOCH_S = 946_684_800.0
VIEWPORT = (1600, 1000)
#: The log the tests open: a lockstep gps-loss run (seed 1) cut to 33-37 s; the GPS goes off at 34 s.
FIXTURE = REPO / "tests" / "fixtures" / "gps-loss-33-37s.mcap"
FIXTURE_SPAN_S = (33.0, 37.0)
#: The layout's panels, by their ids in docs/foxglove-layout.json.
CAMERA, DEPTH, SCENE3D = "Image!camera", "Image!depth", "3D!scene"
PLOTS = ("Plot!formation", "Plot!relative", "Plot!setpoint")


def app_dir() -> Path:
    return Path(os.environ.get("LICHTBLICK_WEB", REPO.parent / "shared" / "lichtblick-web"))


def chromium() -> str | None:
    exe = (
        os.environ.get("LICHTBLICK_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    )
    return exe if exe and Path(exe).exists() else None


def missing() -> str | None:
    """Why the viewer cannot run here, in one line; None when it can."""
    app = app_dir()
    if not (app / "serve.py").is_file() or not (app / "www" / "index.html").is_file():
        return f"no Lichtblick web build at {app} (set LICHTBLICK_WEB)"
    if chromium() is None:
        return "no chromium on PATH (apt-get install chromium, or set LICHTBLICK_CHROMIUM)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install -e '.[dev]')"
    return None


def filter_mcap(
    src: Path,
    dst: Path,
    *,
    start_s: float | None = None,
    end_s: float | None = None,
    drop_topics: frozenset[str] | set[str] = frozenset(),
) -> int:
    """Copy the messages of ``src`` logged in [start_s, end_s] (s from its first message) but ``drop_topics``.

    Every schema and channel that keeps a message is written as it was; returns the message count.
    """
    from mcap.reader import make_reader
    from mcap.writer import Writer

    n = 0
    with src.open("rb") as f, dst.open("wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        t0 = summary.statistics.message_start_time
        writer = Writer(g)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, msg in reader.iter_messages(
            starting_at=None if start_s is None else t0 + int(start_s * 1e9),
            ending_at=None if end_s is None else t0 + int(end_s * 1e9),
            log_time_order=True,
        ):
            if channel.topic in drop_topics:
                continue
            assert schema is not None
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            writer.add_message(channels[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
            n += 1
        writer.finish()
    return n


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def serve(directory: Path | None = None, layout: Path | None = None) -> Iterator[str]:
    """The app's ``serve.py`` on a free port (the app's www/, or ``directory``): yields its base URL."""
    args = [sys.executable, str(app_dir() / "serve.py"), "--bind", "127.0.0.1"]
    args += ["--directory", str(directory)] if directory is not None else []
    args += ["--layout", str(layout)] if layout is not None else []
    for _ in range(5):
        port = _free_port()
        proc = subprocess.Popen(
            [*args, "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
        )
        assert proc.stdout is not None
        line = proc.stdout.readline().decode()
        if line.startswith("serving"):
            break
        proc.wait(timeout=5)  # the port was taken between the probe and the bind: another one
    else:
        raise RuntimeError(f"serve.py did not start: {line}")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


def log_url(app_url: str, mcap_url: str) -> str:
    return f"{app_url}/?ds=remote-file&ds.url={urllib.parse.quote(mcap_url, safe='')}"


def live_url(app_url: str, ws_url: str) -> str:
    return f"{app_url}/?ds=foxglove-websocket&ds.url={urllib.parse.quote(ws_url, safe='')}"


@dataclass
class Shot:
    """One screenshot (RGB) with the panels' rectangles in it (x, y, w, h; CSS pixels = image pixels)."""

    rgb: np.ndarray
    panels: dict[str, tuple[int, int, int, int]]
    #: Each panel's visible text at the same moment (its notices: "Waiting for ...", "Missing transform ...").
    texts: dict[str, str] = field(default_factory=dict)

    def panel(self, panel_id: str) -> np.ndarray:
        """The panel's content, without its toolbar (the top 30 px)."""
        x, y, w, h = self.panels[panel_id]
        return self.rgb[y + 30 : y + h, x : x + w]

    def save(self, path: Path) -> None:
        """A PNG with a reduced palette: the docs' pictures stay small."""
        from PIL import Image

        Image.fromarray(self.rgb).quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(
            path, optimize=True
        )


_PANELS_JS = """() => {
  const out = {};
  for (const el of document.querySelectorAll('[data-testid^="panel-mouseenter-container"]')) {
    const id = el.getAttribute('data-testid').split(' ').slice(1).join(' ');
    const r = el.getBoundingClientRect();
    out[id] = [Math.round(r.x), Math.round(r.y), Math.round(r.width), Math.round(r.height)];
  }
  return out;
}"""


_PANEL_TEXTS_JS = """() => {
  const out = {};
  for (const el of document.querySelectorAll('[data-testid^="panel-mouseenter-container"]')) {
    out[el.getAttribute('data-testid').split(' ').slice(1).join(' ')] = el.innerText;
  }
  return out;
}"""


@dataclass
class Viewer:
    """One headless Chromium page on the app; ``console`` keeps the page's errors."""

    page: Any
    console: list[str] = field(default_factory=list)

    def open(self, url: str, *, playable: bool = True, timeout_s: float = 90.0) -> None:
        """Load the app and wait for the layout's panels (and for a log, the Play button)."""
        self.page.goto(url)
        self.page.locator('[data-testid^="panel-mouseenter-container"]').first.wait_for(
            timeout=timeout_s * 1000
        )
        if playable:
            self.page.get_by_role("button", name="Play", exact=True).wait_for(timeout=timeout_s * 1000)

    def wait_for(self, ready: Callable[[Shot, dict[str, str]], bool], timeout_s: float) -> Shot:
        """A screenshot a second until ``ready(shot, panel texts)``: that shot (the last one at timeout)."""
        deadline = time.monotonic() + timeout_s
        while True:
            shot = self.shot()
            if ready(shot, shot.texts) or time.monotonic() > deadline:
                return shot
            time.sleep(1.0)

    def play(self, timeout_s: float = 60.0) -> None:
        """Press Play until the log plays (a press while the app still loads the log is lost)."""
        controls = self.page.locator('[data-testid="playback-controls"]')
        before = controls.inner_text()
        deadline = time.monotonic() + timeout_s
        while True:
            button = self.page.get_by_role("button", name="Play", exact=True)
            if button.is_visible():
                button.click()
            time.sleep(1.0)
            if self.page.get_by_role("button", name="Pause", exact=True).is_visible():
                return
            if controls.inner_text() != before:  # played, maybe to the end already
                return
            if time.monotonic() > deadline:
                raise AssertionError(f"the log does not play: {before!r}")

    def wait_playing(self, seconds: float) -> None:
        """Let the log play ``seconds`` of real time."""
        time.sleep(seconds)

    def panel_texts(self) -> dict[str, str]:
        """Each panel's visible text (its notices: "Waiting for ...", "Missing transform ...")."""
        return dict(self.page.evaluate(_PANEL_TEXTS_JS))

    def shot(self) -> Shot:
        png = self.page.screenshot()
        bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        return Shot(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), self.page.evaluate(_PANELS_JS), self.panel_texts())

    def alerts(self) -> list[str]:
        """The Alerts tab's entries (empty: "No alerts found"); leaves the tab open."""
        self.page.get_by_role("tab", name="Alerts").click()
        time.sleep(1.0)
        text = self.page.locator("body").inner_text(timeout=10000)
        if "No alerts found" in text:
            return []
        return [line for line in text.splitlines() if line.strip()]


@contextmanager
def viewer() -> Iterator[Viewer]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=chromium(),
            headless=True,
            # WebGL (the 3D panel) on SwiftShader, the CPU renderer: no GPU here.
            args=[
                "--no-sandbox",
                "--use-gl=swiftshader",
                "--enable-unsafe-swiftshader",
                "--ignore-gpu-blocklist",
            ],
        )
        try:
            page = browser.new_page(viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]})
            v = Viewer(page)
            page.on("console", lambda m: m.type == "error" and v.console.append(m.text[:300]))
            page.on("pageerror", lambda e: v.console.append(str(e)[:300]))
            yield v
        finally:
            browser.close()


# -- what a person would see, from the pixels -------------------------------------------------------------


def colour_px(region: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> int:
    """Pixels of ``region`` within ``tol`` of the colour ``rgb`` on every channel."""
    d = np.abs(region.astype(np.int16) - np.array(rgb, np.int16)).max(axis=2)
    return int((d <= tol).sum())


def hue_px(
    region: np.ndarray, hues_deg: tuple[tuple[float, float], ...], min_sat: int = 120, min_val: int = 120
) -> int:
    """Saturated, bright pixels of ``region`` with a hue in one of the [lo, hi] ranges, degrees."""
    hsv = cv2.cvtColor(np.ascontiguousarray(region), cv2.COLOR_RGB2HSV)  # OpenCV's hue: 0-179
    h = hsv[..., 0].astype(np.float32) * 2.0
    in_hue = np.zeros(h.shape, bool)
    for lo, hi in hues_deg:
        in_hue |= (h >= lo) & (h <= hi)
    return int((in_hue & (hsv[..., 1] >= min_sat) & (hsv[..., 2] >= min_val)).sum())


def distinct_colours(region: np.ndarray) -> int:
    """Distinct colours after quantising each channel to 16 levels."""
    q = (region[..., :3] // 16).reshape(-1, 3).astype(np.int32)
    return len(np.unique(q[:, 0] * 256 + q[:, 1] * 16 + q[:, 2]))


#: Colours as the layout draws them (companion/viz/messages.py), as hue ranges in degrees that the 3D
#: renderer's shading keeps: the follower (blue), the leader (red), the formation slot (cyan wire box).
#: The tracked leader's box in the camera panel is green, (26, 230, 51).
LEADER_BOX_RGB = (26, 230, 51)
FOLLOWER_HUES, LEADER_HUES, SLOT_HUES = ((205.0, 230.0),), ((0.0, 12.0), (348.0, 360.0)), ((182.0, 198.0),)
#: Notices a panel shows over its content when the log does not give it what it needs.
PANEL_NOTICES = ("Missing transform", "not found", "Waiting for", "No messages", "Unknown panel type")


def check_panels(shot: Shot, texts: dict[str, str]) -> dict[str, str]:
    """What a person would miss in the layout's panels, by check; empty when every panel shows its data.

    ``camera``: the frame drawn (>= 100 colours) with the tracked leader's green box (>= 40 px); ``depth``:
    the depth image drawn (>= 5000 near-black px: no depth) with colour-mapped depth (>= 15 saturated px,
    the leader at 0-10 m); ``3d``: >= 20 px each of the follower, the leader and the slot, and no notice;
    one per plot: >= 150 px of coloured lines; ``notices``: an image panel's "Waiting for ...", ...
    """
    problems: dict[str, str] = {}
    for panel_id in (CAMERA, DEPTH, SCENE3D, *PLOTS):
        if panel_id not in shot.panels:
            problems[panel_id] = "not in the page"
    if problems:
        return problems

    cam = shot.panel(CAMERA)
    box = colour_px(cam, LEADER_BOX_RGB, tol=50)
    colours = distinct_colours(cam)
    if colours < 100 or box < 40:
        problems["camera"] = f"{colours} colours, {box} px of the leader box's green"
    depth = shot.panel(DEPTH)
    dark = int((depth.max(axis=2) < 20).sum())
    mapped = hue_px(depth, ((0.0, 360.0),))
    if dark < 5000 or mapped < 15:
        problems["depth"] = f"{dark} px without depth, {mapped} px colour-mapped"
    scene = shot.panel(SCENE3D)
    counts = {
        "follower": hue_px(scene, FOLLOWER_HUES, min_sat=100, min_val=100),
        "leader": hue_px(scene, LEADER_HUES, min_sat=100, min_val=100),
        "slot": hue_px(scene, SLOT_HUES, min_sat=100, min_val=100),
    }
    notices = [n for n in PANEL_NOTICES if n in texts.get(SCENE3D, "")]
    if min(counts.values()) < 20 or notices:
        problems["3d"] = f"px {counts}" + (f", notices {notices}" if notices else "")
    for panel_id in PLOTS:
        lines = hue_px(shot.panel(panel_id), ((0.0, 360.0),), min_sat=90, min_val=120)
        if lines < 150:
            problems[panel_id] = f"{lines} px of coloured lines"
    # The image panels' notices ("Waiting for messages..."); a raw-message panel of a 1-Hz topic waits for
    # its next message after every seek, which is no fault.
    other = {p: [n for n in PANEL_NOTICES if n in t] for p, t in texts.items() if p in (CAMERA, DEPTH)}
    if any(other.values()):
        problems["notices"] = str({p: n for p, n in other.items() if n})
    return problems


@dataclass
class LiveFlight:
    """``sitl serve`` and ``companion run`` with the live view: where to connect, the service's state."""

    ws_url: str
    status_sock: Path
    logs: Callable[[], str]

    def state(self) -> str | None:
        from companion.service.status import ServiceNotRunningError, query_status

        try:
            return str(query_status(self.status_sock, timeout_s=2.0)["mission"]["state"])
        except (ServiceNotRunningError, KeyError, TypeError):
            return None

    def wait_state(self, states: tuple[str, ...], timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while (state := self.state()) not in states:
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"the service never reached {states} (last {state}):\n{self.logs()[-3000:]}"
                )
            time.sleep(0.5)
        assert state is not None
        return state


@contextmanager
def live_flight(tmp_path: Path, scenario_toml: str | None = None) -> Iterator[LiveFlight]:
    """The simulator (the service tests' scenario, or ``scenario_toml``) and ``companion run`` beside it.

    The service flies the follower with the simulator's truth boxes as its detector and serves the live view
    on a free port; both processes are stopped by their PIDs whatever happens.
    """
    import asyncio

    from companion.lab.evaluation.procs import Child
    from tests.service.sitl_service import SCENARIO, Ports, service_config, sim_process

    ports = Ports.pick()
    cam = tmp_path / "cam.sock"
    ws_port = _free_port()
    sim = sim_process(tmp_path, ports, cam, scenario_toml or SCENARIO)
    cfg = service_config(tmp_path, ports.follower_api, cam, None, f"[viz]\nlive = true\nport = {ws_port}\n")
    svc = Child(
        [sys.executable, "-m", "companion", "run", "--config", str(cfg)],
        {**os.environ, "PYTHONPATH": str(REPO)},
        tmp_path / "service.log",
    )

    def logs() -> str:
        return svc.log()[-3000:] + "\n--- sitl ---\n" + sim.log()[-1500:]

    try:
        sim.start()
        deadline = time.monotonic() + 90
        while not ("running at" in sim.log() and cam.exists()):
            if time.monotonic() > deadline or not sim.running:
                raise AssertionError(f"the simulator did not start:\n{logs()}")
            time.sleep(0.2)
        svc.start()
        yield LiveFlight(f"ws://127.0.0.1:{ws_port}", tmp_path / "run" / "status.sock", logs)
    finally:
        asyncio.run(svc.stop())
        asyncio.run(sim.stop())


def _cli() -> int:
    p = argparse.ArgumentParser(prog="python -m tests.viz.lichtblick", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cut", help="a span of a log into a new MCAP")
    c.add_argument("src", type=Path)
    c.add_argument("dst", type=Path)
    c.add_argument("start_s", type=float)
    c.add_argument("end_s", type=float)
    sub.add_parser(
        "fixture", help=f"fly the lockstep gps-loss run and cut {FIXTURE_SPAN_S} s of it to the fixture"
    )
    s = sub.add_parser("log", help="screenshot of a log opened with the shipped layout, played")
    s.add_argument("mcap", type=Path)
    s.add_argument("out", type=Path)
    s.add_argument("--play", type=float, default=3.0, help="real seconds of playing before the screenshot")
    live = sub.add_parser(
        "live", help="screenshot of the live view while companion run flies beside sitl serve"
    )
    live.add_argument("out", type=Path)
    live.add_argument("--scenario", type=Path, default=REPO / "config" / "scenarios" / "gps-loss.toml")
    live.add_argument("--state", default="follow_vision", help="the mission state to take the screenshot in")
    live.add_argument("--after", type=float, default=3.0, help="real seconds in that state before it")
    a = p.parse_args()
    if a.cmd == "cut":
        print(f"{filter_mcap(a.src, a.dst, start_s=a.start_s, end_s=a.end_s)} messages to {a.dst}")
        return 0
    if a.cmd == "fixture":
        with tempfile.TemporaryDirectory() as tmp:
            # The GPS goes off at 34 s (config/scenarios/gps-loss.toml): formation from 24 s, 14 s of it.
            subprocess.run(
                [sys.executable, "-m", "companion", "sim", "--scenario", "gps-loss", "--seed", "1",
                 "--harness", "lockstep", "--duration", "14", "--no-plots", "--out", tmp],
                cwd=REPO,
                check=True,
            )  # fmt: skip
            start_s, end_s = FIXTURE_SPAN_S
            n = filter_mcap(Path(tmp) / "flight.mcap", FIXTURE, start_s=start_s, end_s=end_s)
        print(f"{n} messages to {FIXTURE} ({FIXTURE.stat().st_size // 1000} kB)")
        return 0
    why = missing()
    if why is not None:
        print(why, file=sys.stderr)
        return 1
    if a.cmd == "live":
        with tempfile.TemporaryDirectory() as tmp, live_flight(Path(tmp), a.scenario.read_text()) as flight:
            flight.wait_state((a.state,), 300)
            with serve(layout=LAYOUT) as app_url, viewer() as v:
                v.open(live_url(app_url, flight.ws_url), playable=False)
                time.sleep(a.after)
                shot = v.wait_for(lambda shot, texts: not check_panels(shot, texts), 60)
                problems = check_panels(shot, shot.texts)
                alerts = v.alerts()
        return _saved(shot, a.out, problems, alerts)
    mcap = a.mcap.resolve()
    with serve(layout=LAYOUT) as app_url, serve(directory=mcap.parent) as files, viewer() as v:
        v.open(log_url(app_url, f"{files}/{mcap.name}"))
        v.play()
        v.wait_playing(a.play)
        shot = v.wait_for(lambda shot, texts: not check_panels(shot, texts), 90)
        problems = check_panels(shot, shot.texts)
        alerts = v.alerts()
    return _saved(shot, a.out, problems, alerts)


def _saved(shot: Shot, out: Path, problems: dict[str, str], alerts: list[str]) -> int:
    """Write the screenshot and say what it shows (the CLI's exit status)."""
    shot.save(out)
    size_kb = out.stat().st_size // 1000
    print(f"{out}: {size_kb} kB; panels {problems or 'all filled'}; alerts {alerts or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(_cli())
