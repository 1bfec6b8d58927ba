"""TEST-ONLY ``sitl serve`` component: streams ground truth of every vehicle to the test over UDP.

``python -m tests.flight.truth_component serve ...`` is ``sitl`` with :func:`serve_truth` passed in; the
destination port comes from ``WINGMAN_TEST_TRUTH_PORT``. One JSON datagram every 20 ms of sim time:
``{"t_s": ..., "vehicles": {name: {"p": [n, e, d], "v": [...], "q": [w, x, y, z]}}}`` in the world NED frame.
It exists so flight tests can drive the formation law from the true relative state until the perception
pipeline is wired in; figures flown this way are never vision results.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from typing import Any

PERIOD_S = 0.02


async def serve_truth(sim: Any) -> None:
    """Send truth until cancelled."""
    port = int(os.environ["WINGMAN_TEST_TRUTH_PORT"])
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    try:
        t_s = sim.t_s
        while True:
            t_s += PERIOD_S
            await sim.wait_until(t_s)
            vehicles = {}
            for name in sim.names:
                tr = sim.truth(name)
                vehicles[name] = {
                    "p": [float(x) for x in tr.p_ned_m],
                    "v": [float(x) for x in tr.v_ned_m_s],
                    "q": [float(x) for x in tr.q_ned_body_wxyz],
                }
            payload = json.dumps({"t_s": float(sim.t_s), "vehicles": vehicles}).encode()
            with contextlib.suppress(OSError):  # nobody listening yet
                sock.sendto(payload, ("127.0.0.1", port))
    finally:
        sock.close()


if __name__ == "__main__":
    from sitl.cli import main

    raise SystemExit(main(components=(serve_truth,)))
