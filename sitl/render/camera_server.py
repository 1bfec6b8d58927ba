"""The simulated camera inside ``sitl serve``: renders the follower's view on the sim clock and streams it.

:class:`CameraServer` samples the truth callable every ``1 / rate_hz`` sim seconds, has the frame
rendered by a worker process (:mod:`sitl.render.worker`: moderngl holds the GIL while the driver
renders, which would stall the simulator's real-time loop) and forwards it to every connected client
over a Unix socket, in the wire format of :mod:`companion.kernel.camera_wire`. A client that falls
behind loses frames rather than building a backlog. Nothing is rendered while no client is connected.

``sitl serve`` runs it unless ``--no-camera`` (``--camera PATH``, default ``/run/wingman/camera.sock``),
with the scenario's ``[visual]`` table, for the vehicles named ``follower`` and ``leader``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sys
from asyncio.subprocess import PIPE
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

from companion.kernel.camera import MountConfig
from companion.kernel.camera_wire import PREFIX, DepthEncoding
from companion.kernel.errors import CameraError
from sitl.render.config import CameraModel, VisualConfig, visual_from_mapping
from sitl.render.faults import DepthGlitches
from sitl.render.geometry import PoseTruth
from sitl.render.worker import READY, pose_to_json

log = logging.getLogger(__name__)

DEFAULT_SOCKET = Path("/run/wingman/camera.sock")
TruthFn = Callable[[], tuple[PoseTruth, PoseTruth | None]]
#: A client whose unsent data exceeds this many frames gets frames dropped until it catches up.
MAX_QUEUED_FRAMES = 2
#: The render process imports numpy and moderngl and bakes the world before it is ready.
STARTUP_TIMEOUT_S = 60.0


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
        depth_glitches: Sequence[tuple[float, float]] = (),
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
        self._glitches = DepthGlitches(depth_glitches)
        self.frames_sent = 0
        self.frames_dropped = 0
        self._clients: set[asyncio.StreamWriter] = set()
        self._proc: asyncio.subprocess.Process | None = None
        self._server: asyncio.Server | None = None

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def __aenter__(self) -> Self:
        try:
            self._proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "sitl.render.worker", stdin=PIPE, stdout=PIPE
            )
            assert self._proc.stdin is not None  # noqa: S101 (PIPE)
            cfg = {
                "camera": self.camera.model_dump(mode="json"),
                "visual": self.visual.model_dump(mode="json"),
                "mount": self.mount.model_dump(mode="json"),
                "seed": self.seed,
                "depth": self.depth_encoding,
            }
            self._proc.stdin.write(json.dumps(cfg).encode() + b"\n")
            await self._proc.stdin.drain()
            async with asyncio.timeout(STARTUP_TIMEOUT_S):
                ready = await self._worker_out().readexactly(len(READY))
            if ready != READY:
                raise CameraError(f"camera render process: unexpected greeting {ready!r}")
            self.socket_path.parent.mkdir(parents=True, exist_ok=True)
            self._server = await asyncio.start_unix_server(self._on_client, path=str(self.socket_path))
        except asyncio.IncompleteReadError:
            await self._shutdown()
            raise CameraError("camera render process exited while starting (see its stderr)") from None
        except BaseException:
            await self._shutdown()
            raise
        log.info("camera server on %s at %.0f Hz", self.socket_path, self.rate_hz)
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self._shutdown()

    def _worker_out(self) -> asyncio.StreamReader:
        assert self._proc is not None  # noqa: S101 (inside the context)
        assert self._proc.stdout is not None  # noqa: S101 (PIPE)
        return self._proc.stdout

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for w in list(self._clients):
            w.close()
        self._clients.clear()
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.stdin is not None:
                proc.stdin.close()  # EOF: the worker leaves its loop and releases the GL context

            async def drained_exit() -> None:
                # A frame cut short by cancellation may still be in the pipe: read it away, or the
                # worker blocks writing it, and asyncio's wait() also needs stdout at EOF to return.
                if proc.stdout is not None:
                    while await proc.stdout.read(1 << 16):
                        pass
                await proc.wait()

            try:
                async with asyncio.timeout(5.0):
                    await drained_exit()
            except TimeoutError:
                proc.kill()
                await drained_exit()
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

    async def _render(self, follower: PoseTruth, leader: PoseTruth | None, t_s: float) -> list[bytes]:
        """One frame from the worker, as the raw wire message (prefix + header, rgb, depth)."""
        assert self._proc is not None  # noqa: S101 (inside the context)
        assert self._proc.stdin is not None  # noqa: S101 (PIPE)
        req = {
            "t": t_s,
            "f": pose_to_json(follower),
            "l": None if leader is None else pose_to_json(leader),
            "dz": self._glitches.take(t_s),
        }
        self._proc.stdin.write(json.dumps(req).encode() + b"\n")
        out = self._worker_out()
        try:
            await self._proc.stdin.drain()
            prefix = await out.readexactly(PREFIX.size)
            _, n = PREFIX.unpack(prefix)
            raw = await out.readexactly(n)
            header = json.loads(raw)
            rgb = await out.readexactly(int(header["rgb_bytes"]))
            depth = await out.readexactly(int(header["depth_bytes"]))
        except (asyncio.IncompleteReadError, ConnectionError):
            code = self._proc.returncode
            raise CameraError(f"camera render process died (exit code {code}; see its stderr)") from None
        return [prefix + raw, rgb, depth]

    async def run(self) -> None:
        """Render and send frames at ``rate_hz`` of sim time until cancelled."""
        if self._proc is None:
            raise RuntimeError("CameraServer.run() outside `async with`")
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
            payload = await self._render(follower, leader, t_s)
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
    """What ``sitl serve`` hands its components (see ``sitl.serve.server.SimHandle``)."""

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


#: The camera on its default socket, for a program that hosts the simulator (``sitl.cli.main``).
camera_component = make_camera_component()
