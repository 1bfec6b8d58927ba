"""The simulated camera inside ``sitl serve``: renders the follower's view on the sim clock and streams it.

:class:`CameraServer` samples the truth callable every ``1 / rate_hz`` sim seconds, renders on one
worker thread (which owns the GL context, so the event loop keeps running meanwhile) and writes each
frame to every connected client over a Unix socket, in the wire format of
:mod:`companion.perception.sources.sim`. A client that falls behind loses frames rather than building
a backlog. Nothing is rendered while no client is connected.

In ``sitl serve`` add ``components = ["sitl.render.server:camera_component"]`` to ``[serve]`` (or pass
``--component sitl.render.server:camera_component``): it serves ``/run/wingman/camera.sock`` with the
scenario's ``[visual]`` table, for the vehicles named ``follower`` and ``leader``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

import numpy as np

from companion.config import MountConfig
from companion.perception.sources.sim import DepthEncoding, encode_frame
from sitl.render.config import CameraModel, VisualConfig, visual_from_mapping
from sitl.render.geometry import PoseTruth, VehiclePose, as_vec3
from sitl.render.renderer import Renderer

log = logging.getLogger(__name__)

DEFAULT_SOCKET = Path("/run/wingman/camera.sock")
TruthFn = Callable[[], tuple[PoseTruth, PoseTruth | None]]
#: A client whose unsent data exceeds this many frames gets frames dropped until it catches up.
MAX_QUEUED_FRAMES = 2


def _snapshot(truth: PoseTruth) -> VehiclePose:
    """Copy the pose (and rate, when present) so the render thread never sees the sim mutate it."""
    omega = getattr(truth, "omega_body_rad_s", None)
    return VehiclePose(
        as_vec3(truth.p_ned_m).copy(),
        np.array(truth.q_ned_body_wxyz, dtype=np.float64),
        None if omega is None else as_vec3(omega).copy(),
    )


class CameraServer:
    """Streams the follower's rendered RGB-D camera over a Unix socket, on the simulation's clock.

    Args:
        socket_path: where to listen (its folder is created; a stale socket file is replaced).
        truth_fn: returns (follower truth, leader truth or None) at the current sim time; anything with
            ``p_ned_m`` and ``q_ned_body_wxyz`` (and optionally ``omega_body_rad_s``) will do.
        time_fn: the current sim time, s.
        rate_hz: frames per sim second (default: the camera's 30 Hz).
        wait_until: awaits until sim time reaches the argument (``SimHandle.wait_until``); without it
            the server polls ``time_fn`` every few milliseconds.
        depth_encoding: "u16_mm" (RealSense-like, half the bytes) or "f32_m".
    """

    def __init__(
        self,
        socket_path: str | Path,
        truth_fn: TruthFn,
        time_fn: Callable[[], float],
        *,
        rate_hz: float | None = None,
        camera: CameraModel | None = None,
        visual: VisualConfig | None = None,
        mount: MountConfig | None = None,
        seed: int = 0,
        depth_encoding: DepthEncoding = "u16_mm",
        wait_until: Callable[[float], Awaitable[None]] | None = None,
    ) -> None:
        self.socket_path = Path(socket_path)
        self.truth_fn = truth_fn
        self.time_fn = time_fn
        self.camera = camera or CameraModel()
        self.rate_hz = rate_hz or self.camera.rate_hz
        self.visual = visual or VisualConfig()
        self.mount = mount or MountConfig()
        self.seed = seed
        self.depth_encoding: DepthEncoding = depth_encoding
        self._wait_until = wait_until or self._poll_until
        #: Fault injection: while True the camera delivers nothing (a stalled driver), time goes on.
        self.stalled = False
        self.frames_sent = 0
        self.frames_dropped = 0
        self._clients: set[asyncio.StreamWriter] = set()
        self._executor: ThreadPoolExecutor | None = None
        self._renderer: Renderer | None = None
        self._server: asyncio.Server | None = None

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def __aenter__(self) -> Self:
        loop = asyncio.get_running_loop()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sitl.camera")
        try:
            self._renderer = await loop.run_in_executor(
                self._executor, lambda: Renderer(self.camera, self.visual, self.mount, seed=self.seed)
            )
            self.socket_path.parent.mkdir(parents=True, exist_ok=True)
            self._server = await asyncio.start_unix_server(self._on_client, path=str(self.socket_path))
        except BaseException:
            await self._shutdown()
            raise
        log.info("camera server on %s at %.0f Hz", self.socket_path, self.rate_hz)
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self._shutdown()

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for w in list(self._clients):
            w.close()
        self._clients.clear()
        if self._executor is not None:
            if self._renderer is not None:
                await asyncio.get_running_loop().run_in_executor(self._executor, self._renderer.close)
                self._renderer = None
            self._executor.shutdown(wait=True)
            self._executor = None
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        log.info("camera client connected (%d)", len(self._clients))
        try:
            while await reader.read(4096):  # clients send nothing; EOF means they left
                pass
        except ConnectionError:
            pass
        finally:
            self._clients.discard(writer)
            writer.close()

    async def _poll_until(self, t_s: float) -> None:
        # Without a wait_until from the simulator there is no event to wait on: poll its clock.
        while (remaining := t_s - self.time_fn()) > 0:  # noqa: ASYNC110
            await asyncio.sleep(min(remaining, 0.005))

    def _render_encoded(self, follower: PoseTruth, leader: PoseTruth | None, t_s: float) -> list[Any]:
        assert self._renderer is not None  # noqa: S101 (inside the context)
        return encode_frame(self._renderer.render(follower, leader, t_s), self.depth_encoding)

    async def run(self) -> None:
        """Render and send frames at ``rate_hz`` of sim time until cancelled."""
        if self._executor is None:
            raise RuntimeError("CameraServer.run() outside `async with`")
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        next_t = self.time_fn()
        while True:
            await self._wait_until(next_t)
            t_s = self.time_fn()
            next_t += period
            if next_t <= t_s:  # fell behind (slow host, long render): skip missed frames, no burst
                next_t = t_s + period
            if self.stalled or not self._clients:
                continue
            follower, leader = self.truth_fn()
            snap_f, snap_l = _snapshot(follower), None if leader is None else _snapshot(leader)
            payload = await loop.run_in_executor(self._executor, self._render_encoded, snap_f, snap_l, t_s)
            frame_bytes = sum(len(p) for p in payload)
            for w in list(self._clients):
                if w.is_closing():
                    self._clients.discard(w)
                elif w.transport.get_write_buffer_size() > MAX_QUEUED_FRAMES * frame_bytes:
                    self.frames_dropped += 1
                else:
                    w.writelines(payload)
                    self.frames_sent += 1


class _SimHandle(Protocol):
    """What ``sitl serve`` hands its components (see ``sitl.serve.SimHandle``)."""

    @property
    def t_s(self) -> float: ...

    @property
    def names(self) -> tuple[str, ...]: ...

    @property
    def scenario(self) -> Any: ...

    def truth(self, name: str) -> Any: ...

    async def wait_until(self, t_s: float) -> None: ...


def make_camera_component(
    socket_path: str | Path = DEFAULT_SOCKET, follower: str = "follower", leader: str = "leader"
) -> Callable[[_SimHandle], Awaitable[None]]:
    """A ``sitl serve`` component running a :class:`CameraServer` for the named vehicles."""

    async def component(sim: _SimHandle) -> None:
        names = sim.names
        f_name = follower if follower in names else names[-1]
        l_name = leader if leader in names and leader != f_name else None
        scenario = sim.scenario
        raw = getattr(scenario, "visual", None) if scenario is not None else None
        visual = visual_from_mapping(raw, f"scenario {getattr(scenario, 'name', '')} [visual]")
        seed = int(getattr(scenario, "seed", 0) or 0) if scenario is not None else 0

        def truth() -> tuple[PoseTruth, PoseTruth | None]:
            return sim.truth(f_name), None if l_name is None else sim.truth(l_name)

        async with CameraServer(
            socket_path, truth, lambda: sim.t_s, visual=visual, seed=seed, wait_until=sim.wait_until
        ) as server:
            await server.run()

    return component


#: The default component: ``--component sitl.render.server:camera_component``.
camera_component = make_camera_component()
