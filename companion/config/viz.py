"""``[viz]``: the live view (Foxglove WebSocket) and the flight logs (MCAP), both off by default."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.kernel.config import Section


class VizConfig(Section):
    """What the follower sees, live and afterwards, in Foxglove or Lichtblick (docs/visualisation.md)."""

    #: Serve the live view over Foxglove's WebSocket protocol.
    live: bool = False
    #: Address and port the live view listens on. 127.0.0.1 keeps it on the drone (reach it through an
    #: SSH tunnel); 0.0.0.0 serves every network the drone is on, to anyone who can reach it.
    host: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)
    #: Colour images (JPEG) to viewers at most this often, Hz; depth images at most ``live_depth_rate_hz``.
    live_image_rate_hz: float = Field(10.0, gt=0.0, le=60.0)
    live_depth_rate_hz: float = Field(2.0, ge=0.0, le=60.0)
    jpeg_quality: int = Field(80, ge=10, le=100)
    #: Write an MCAP flight log per service start.
    log: bool = False
    #: Folder of the flight logs; empty: ``flights/`` in ``service.state_dir``.
    log_dir: str = ""
    #: Colour and depth images into the log at most this often, Hz; 0: every frame the detector saw.
    log_image_rate_hz: float = Field(10.0, ge=0.0, le=60.0)
    #: ``jpeg`` (small) or ``png`` (lossless: ``companion replay`` of the log sees what the detector saw).
    log_image_format: Literal["jpeg", "png"] = "jpeg"
    #: Depth images in the log (16-bit millimetres, as a RealSense gives them).
    log_depth: bool = True
    #: A log file is closed and the next one opened beyond this size, bytes.
    log_file_max_bytes: int = Field(512_000_000, ge=1_000_000)
    #: The oldest log files are deleted to keep the folder under this size, bytes.
    log_budget_bytes: int = Field(4_000_000_000, ge=1_000_000)
