"""TEST-ONLY ``sitl serve`` component: the renderer's camera server on the socket the test chose.

``python -m tests.service.sitl_camera serve ...`` is ``sitl`` with :func:`camera` passed in; the socket path
comes from ``WINGMAN_TEST_CAMERA_SOCK``. The camera is smaller and slower than the D435i default
(320x240 at 15 Hz, no scattered structures) so that simulator, renderer and service keep real time on a
2-core test machine; the service's pipeline is the same at any resolution.
"""

from __future__ import annotations

import os
from typing import Any

from sitl.render.camera_server import CameraServer
from sitl.render.config import CameraModel, VisualConfig


async def camera(sim: Any) -> None:
    def truth() -> tuple[Any, Any]:
        return sim.truth("follower"), sim.truth("leader")

    async with CameraServer(
        os.environ["WINGMAN_TEST_CAMERA_SOCK"],
        truth,
        lambda: sim.t_s,
        camera=CameraModel(width_px=640, height_px=480, rate_hz=10.0),
        visual=VisualConfig(structures=0),
        seed=7,
        wait_until=sim.wait_until,
    ) as server:
        await server.run()


if __name__ == "__main__":
    from sitl.cli import main

    raise SystemExit(main(components=(camera,)))
