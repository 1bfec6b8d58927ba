"""Frame sources behind the :class:`~companion.perception.types.FrameSource` protocol.

``open_source(cfg.camera)`` picks one from the config: ``file`` (a folder recording, a RealSense
``.bag`` or ``.db3``, or an ``.mcap`` flight log), ``realsense`` (live) or ``sim`` (the simulator's
rendered camera, owned by ``sitl``).
Nothing is opened until ``async with``; modules with heavy imports load only when chosen.
"""

from __future__ import annotations

from pathlib import Path

from companion.config import CameraConfig
from companion.kernel.clock import Clock
from companion.kernel.errors import CameraError
from companion.perception.types import FrameSource


def parse_source(spec: str, camera: CameraConfig) -> CameraConfig:
    """Apply a command-line ``--source`` (``sim``, ``realsense`` or ``file:PATH``) to a camera config."""
    if spec in ("sim", "realsense"):
        return camera.model_copy(update={"source": spec})
    if spec.startswith("file:") and len(spec) > len("file:"):
        return camera.model_copy(update={"source": "file", "path": spec[len("file:") :]})
    raise CameraError(f"--source {spec!r}: expected sim, realsense or file:PATH")


def open_source(camera: CameraConfig, *, clock: Clock | None = None) -> FrameSource:
    """The frame source the camera config names (not yet entered)."""
    if camera.source == "file":
        path = Path(camera.path)
        if path.suffix.lower() == ".mcap":
            from companion.perception.sources.mcap_file import McapSource  # noqa: PLC0415

            return McapSource(path, realtime=camera.realtime, loop=camera.loop, clock=clock)
        if path.suffix.lower() in (".bag", ".db3"):
            from companion.perception.sources.bag import BagSource  # noqa: PLC0415

            return BagSource(path, realtime=camera.realtime, loop=camera.loop, clock=clock)
        from companion.perception.sources.file import FolderSource  # noqa: PLC0415

        return FolderSource(path, realtime=camera.realtime, loop=camera.loop, fps=camera.fps, clock=clock)
    if camera.source == "realsense":
        from companion.perception.sources.realsense import RealSenseSource  # noqa: PLC0415

        return RealSenseSource(camera)
    from companion.perception.sources.sim import open_sim_source  # noqa: PLC0415

    return open_sim_source(camera, clock=clock)
