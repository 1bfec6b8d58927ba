"""The live view in Lichtblick: ``companion run`` beside ``sitl serve``, the app on the service's WebSocket.

The service flies the follower (the simulator's truth boxes as its detector) with ``viz.live`` on; once it
follows the leader, the app connects with the shipped layout (``?ds=foxglove-websocket``). Two screenshots
some seconds apart: the second shows every panel filled (the checks of the log's test) and the camera and 3D
panels have changed since the first (the view follows the flight); the Alerts tab is empty.
"""

from __future__ import annotations

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
    with lb.live_flight(tmp_path) as flight, lb.serve(layout=lb.LAYOUT) as app_url, lb.viewer() as v:
        flight.wait_state(("follow",), 150)
        v.open(lb.live_url(app_url, flight.ws_url), playable=False)
        first = v.wait_for(lambda shot, texts: "camera" not in lb.check_panels(shot, texts), 60)
        time.sleep(4.0)
        second = v.wait_for(lambda shot, texts: not lb.check_panels(shot, texts), 30)
        texts = v.panel_texts()
        alerts = v.alerts()
        state = flight.state()
    second.save(tmp_path / "live.png")
    problems = lb.check_panels(second, texts)
    changed = {p: _changed(first.panel(p), second.panel(p)) for p in (lb.CAMERA, lb.SCENE3D)}
    print(f"live: {problems or 'every panel filled'}; changed {changed}; alerts {alerts}; state {state}")
    assert not problems, problems
    assert not alerts, alerts
    assert changed[lb.CAMERA] > 0.02, changed
    assert changed[lb.SCENE3D] > 0.005, changed
