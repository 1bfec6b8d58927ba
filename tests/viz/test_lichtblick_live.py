"""The live view in Lichtblick: ``companion run`` beside ``sitl serve``, the app on the service's WebSocket.

The service flies the follower (the simulator's truth boxes as its detector) with ``viz.live`` on; once it
follows the leader, the app connects with the shipped layout (``?ds=foxglove-websocket``). Two screenshots
some seconds apart: the second shows every panel filled (a frame, the depth image, the follower, the plots'
lines) and the camera and 3D panels have changed since the first (the view follows the flight); the Alerts
tab is empty. It takes about 2 min on a busy 2-core machine: it runs where LICHTBLICK_LIVE=1.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from tests.viz import lichtblick as lb

pytestmark = [pytest.mark.sitl, pytest.mark.render, pytest.mark.slow, pytest.mark.timeout(300)]


def _changed(a: np.ndarray, b: np.ndarray) -> float:
    """Share of the pixels that changed by more than 30 levels on some channel."""
    return float((np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > 30).mean())


def test_the_live_view_in_lichtblick_updates_while_the_follower_flies(tmp_path: Path) -> None:
    why = lb.missing()
    if why is not None:
        pytest.skip(f"Lichtblick in headless Chromium: {why}")
    if os.environ.get("LICHTBLICK_LIVE") != "1":
        pytest.skip("the live view in Lichtblick flies for about 2 min: set LICHTBLICK_LIVE=1 to run it")
    with lb.live_flight(tmp_path) as flight, lb.serve(layout=lb.LAYOUT) as app_url, lb.viewer() as v:
        flight.wait_state(("follow",), 150)
        v.open(lb.live_url(app_url, flight.ws_url), playable=False)
        first = v.wait_for(lambda shot, texts: _filled(shot) == {}, 60)
        time.sleep(4.0)
        second = v.wait_for(lambda shot, texts: _filled(shot) == {}, 30)
        alerts = v.alerts()
        state = flight.state()
    second.save(tmp_path / "live.png")
    problems = _filled(second)
    changed = {p: _changed(first.panel(p), second.panel(p)) for p in (lb.CAMERA, lb.SCENE3D)}
    print(f"live: {problems or 'every panel filled'}; changed {changed}; alerts {alerts}; state {state}")
    assert not problems, problems
    assert not alerts, alerts
    assert changed[lb.CAMERA] > 0.02, changed
    assert changed[lb.SCENE3D] > 0.005, changed


def _filled(shot: lb.Shot) -> dict[str, int]:
    """The panels that show nothing: the camera's frame, the depth image, the follower in 3D, each plot.

    What the flight shows in them (the leader's box, its estimate) depends on how the flight goes on a
    busy machine; the log's test checks that content.
    """
    counts = {
        "camera colours": lb.distinct_colours(shot.panel(lb.CAMERA)),
        "depth px": int((shot.panel(lb.DEPTH).max(axis=2) < 20).sum()),
        "follower px": lb.hue_px(shot.panel(lb.SCENE3D), lb.FOLLOWER_HUES, min_sat=100, min_val=100),
        **{p: lb.hue_px(shot.panel(p), ((0.0, 360.0),), min_sat=90, min_val=120) for p in lb.PLOTS},
    }
    least = {"camera colours": 100, "depth px": 5000, "follower px": 20} | dict.fromkeys(lb.PLOTS, 150)
    return {k: n for k, n in counts.items() if n < least[k]}
