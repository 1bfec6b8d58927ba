"""A flight's MCAP log opened in Lichtblick with the shipped layout, played, and looked at as a person would.

The log is a lockstep ``gps-loss`` run cut to 33-37 s (the GPS goes off at 34 s), committed as a fixture
(tests/fixtures/gps-loss-33-37s.mcap, 1.6 MB; ``python -m tests.viz.lichtblick fixture`` writes it again).
What is checked, from the screenshot's pixels inside each panel of the layout and from the app's Alerts tab:

* the camera panel shows the frame (many colours) with the tracked leader's box (its green);
* the depth panel shows turbo colours (blue to red), not a black field;
* the 3D panel shows the follower (blue), the leader (red) and the formation slot (cyan), with no
  "missing transform" or "frame not found" notice;
* each plot draws its lines (the plot palette's first colours);
* the Alerts tab is empty ("No alerts found": no schema, frame, transform or time problem).

Each check is shown to fail on a broken log or layout: a layout that names a camera topic the log does not
have (the camera check), and the log without ``/tf`` (the 3D check).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

from companion.viz.channels import TOPICS
from tests.viz import lichtblick as lb

FIXTURE = lb.FIXTURE
pytestmark = pytest.mark.timeout(300)


def test_the_fixture_log_has_the_channels_and_schemas_the_service_writes() -> None:
    """The committed log is what the recorder writes today (else regenerate it, see the module's doc)."""
    with FIXTURE.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    got = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    assert set(got) == set(TOPICS)
    for topic, schema in got.items():
        want = TOPICS[topic]
        assert (schema.name, schema.encoding, schema.data) == (
            want.schema_name,
            want.schema_encoding,
            want.schema_data,
        ), f"{topic}: the fixture's schema is not the recorder's; python -m tests.viz.lichtblick fixture"


@pytest.fixture(scope="module")
def app() -> str:
    why = lb.missing()
    if why is not None:
        pytest.skip(f"Lichtblick in headless Chromium: {why}")
    return ""


def _look(layout: Path, mcap: Path, failing: set[str]) -> tuple[lb.Shot, list[str]]:
    """Open ``mcap`` with ``layout`` and play it until a screenshot passes every check but ``failing`` (at
    most 90 s: a busy machine draws slowly): that screenshot, and then the alerts."""
    with lb.serve(layout=layout) as app_url, lb.serve(directory=mcap.parent) as files, lb.viewer() as v:
        v.open(lb.log_url(app_url, f"{files}/{mcap.name}"))
        v.play()
        shot = v.wait_for(lambda shot, texts: set(lb.check_panels(shot, texts)) <= failing, 90)
        return shot, v.alerts()


def _no_tf(tmp_path: Path) -> Path:
    out = tmp_path / "no-tf.mcap"
    lb.filter_mcap(FIXTURE, out, drop_topics={"/tf"})
    return out


def _wrong_camera_layout(tmp_path: Path) -> Path:
    layout = json.loads(lb.LAYOUT.read_text())
    layout["configById"][lb.CAMERA]["imageMode"]["imageTopic"] = "/camera/colour"
    out = tmp_path / "layout.json"
    out.write_text(json.dumps(layout))
    return out


CASES = {
    "shipped": (lambda tmp: lb.LAYOUT, lambda tmp: FIXTURE, set()),
    # The camera panel shows no frame and its "Waiting for messages...".
    "wrong camera topic": (_wrong_camera_layout, lambda tmp: FIXTURE, {"camera", "notices"}),
    "no /tf": (lambda tmp: lb.LAYOUT, _no_tf, {"3d"}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_log_in_lichtblick_shows_every_panel_filled_and_no_alert(
    app: str, case: str, tmp_path: Path
) -> None:
    make_layout, make_log, want_failed = CASES[case]
    shot, alerts = _look(make_layout(tmp_path), make_log(tmp_path), want_failed)
    shot.save(tmp_path / "shot.png")
    problems = lb.check_panels(shot, shot.texts) | ({"alerts": "; ".join(alerts)} if alerts else {})
    print(f"{case}: {problems or 'every check passed'} ({tmp_path / 'shot.png'})")
    assert set(problems) == want_failed, problems
