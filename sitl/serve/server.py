"""``sitl serve``: the lockstep :class:`~sitl.world.lockstep.World` in real time x speed, on MAVLink/UDP.

Each vehicle ``i`` (MAVLink system ``i + 1``) gets PX4 SITL's two links:

* API link: a socket bound to ``api_local_port_base + i`` (14580 + i) that sends to
  ``remote_host:api_remote_port_base + i`` (127.0.0.1:14540 + i), so MAVSDK's
  ``udpin://0.0.0.0:14540`` finds the vehicle exactly as it finds PX4 SITL;
* GCS link: bound to ``gcs_local_port_base + i`` (18570 + i), sending to ``remote_host:14550``
  (QGroundControl, MAVProxy ``--master=udpin:0.0.0.0:14550``).

Each link answers its default remote and any peer heard in the last 10 s, and drops junk datagram by
datagram (:mod:`sitl.serve.udp_link`).

Components: anything else that must live in this process and see the simulation (the renderer's
camera server) is an async callable ``component(sim: SimHandle) -> None``. The simulator's own camera is
``--camera``; a program that hosts the simulator passes its own components in
(``sitl.cli.main(argv, components=...)``, as the lab's real path does): the simulator never imports them
by name. Each runs in the same TaskGroup and reads ground truth through :class:`SimHandle`
(``truth(name)``, ``t_s``, ``wait_until(t_s)``). Ctrl-C or SIGTERM stops everything cleanly.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import signal
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from companion.kernel.errors import CompanionError, ConfigError
from companion.kernel.logs import setup_logging
from companion.kernel.shipped import project_root
from sitl.autopilot.state import GlobalEstimate
from sitl.config import SitlConfig, load_sitl_config
from sitl.physics.dynamics import VehicleTruth
from sitl.serve.udp_link import UdpLink
from sitl.world.lockstep import LINK_API, LINK_GCS, World
from sitl.world.scenario import Scenario, find_scenario, load_scenario

log = logging.getLogger(__name__)

#: If the host cannot keep up, give up on catching up beyond this much sim time (then slip).
MAX_CATCH_UP_S = 0.1
LOOP_PERIOD_S = 0.002

Component = Callable[["SimHandle"], Awaitable[None]]
#: MAV_SEVERITY names, 0 to 7.
SEVERITY = ("emergency", "alert", "critical", "error", "warning", "notice", "info", "debug")


class BindError(CompanionError):
    """A UDP port the simulator needs is taken."""

    exit_code = 3


class SimHandle:
    """What an in-process component may see: the sim clock and ground truth.

    ``truth(name)`` is the true state (world NED frame) at the current sim time; ``t_s`` the sim
    time; ``wait_until(t_s)`` sleeps until the simulation has reached ``t_s``.
    """

    def __init__(self, world: World, speed_factor: float, scenario: Scenario | None) -> None:
        self._world = world
        self.speed_factor = speed_factor
        self.scenario = scenario
        self._advanced = asyncio.Event()

    @property
    def t_s(self) -> float:
        return self._world.t_s

    @property
    def names(self) -> tuple[str, ...]:
        return self._world.names

    def truth(self, name: str) -> VehicleTruth:
        return self._world.truth(name)

    def global_estimate(self, name: str) -> GlobalEstimate | None:
        """The global position ``name``'s autopilot reports (its estimate, not the truth); None before one."""
        return self._world.autopilot(name).global_estimate()

    def mode(self, name: str) -> tuple[str, bool]:
        """The autopilot's flight mode (PX4's UI name) and whether it is armed."""
        return self._world.autopilot(name).mode()

    def status_texts(self, name: str) -> list[tuple[float, str, str]]:
        """The autopilot's STATUSTEXTs so far: (sim time s, severity, text)."""
        return [
            (t_s, SEVERITY[sev] if 0 <= sev < len(SEVERITY) else str(sev), text)
            for t_s, sev, text in self._world.autopilot(name).status_texts()
        ]

    def _notify(self) -> None:
        self._advanced.set()
        self._advanced = asyncio.Event()

    async def wait_until(self, t_s: float) -> None:
        """Return once sim time >= ``t_s``."""
        while self._world.t_s < t_s:
            await self._advanced.wait()


@dataclass(frozen=True, slots=True)
class Endpoint:
    """Where one link talks (for the startup banner)."""

    vehicle: str
    sysid: int
    kind: str
    bind: tuple[str, int]
    remote: tuple[str, int]


def endpoints(cfg: SitlConfig) -> list[Endpoint]:
    """Every UDP endpoint ``cfg`` asks for, PX4 SITL's numbering."""
    m = cfg.mavlink
    out = []
    for i, v in enumerate(cfg.vehicles):
        out.append(
            Endpoint(
                v.name,
                i + 1,
                "api",
                (m.bind_host, m.api_local_port_base + i),
                (m.remote_host, m.api_remote_port_base + i),
            )
        )
        if m.gcs_enabled:
            out.append(
                Endpoint(
                    v.name,
                    i + 1,
                    "gcs",
                    (m.bind_host, m.gcs_local_port_base + i),
                    (m.remote_host, m.gcs_remote_port),
                )
            )
    return out


class Server:
    """Runs a :class:`World` against the wall clock and puts its links on UDP."""

    def __init__(
        self,
        cfg: SitlConfig,
        scenario: Scenario | None,
        *,
        speed_factor: float,
        seed: int | None = None,
        components: Sequence[Component] = (),
    ) -> None:
        self.cfg = cfg
        self.speed_factor = speed_factor
        self.world = World(cfg, scenario, seed=seed, speed_factor=speed_factor, epoch_unix_s=time.time())
        self.sim = SimHandle(self.world, speed_factor, scenario)
        self.components = tuple(components)
        self.udp: list[UdpLink] = []
        self.overruns = 0

    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        for ep in endpoints(self.cfg):
            index = LINK_API if ep.kind == "api" else LINK_GCS
            link = self.world.link(ep.vehicle, index)
            proto = UdpLink(link, ep.sysid, ep.remote, f"{ep.vehicle}/{ep.kind}")
            try:
                await loop.create_datagram_endpoint(lambda p=proto: p, local_addr=ep.bind)  # type: ignore[misc]
            except OSError as exc:
                raise BindError(
                    f"cannot bind UDP {ep.bind[0]}:{ep.bind[1]} ({ep.vehicle} {ep.kind}): {exc.strerror}"
                ) from None
            self.udp.append(proto)
        by_name = {(p.label): p for p in self.udp}
        for proto in self.udp:
            vehicle, _, kind = proto.label.partition("/")
            if kind == "api":
                proto.forward_to = by_name.get(f"{vehicle}/gcs")

    def _close(self) -> None:
        for proto in self.udp:
            if proto.transport is not None:
                proto.transport.close()

    def banner(self) -> list[str]:
        lines = []
        by_vehicle: dict[str, list[Endpoint]] = {}
        for ep in endpoints(self.cfg):
            by_vehicle.setdefault(ep.vehicle, []).append(ep)
        for name, eps in by_vehicle.items():
            parts = []
            for ep in eps:
                hint = f" (MAVSDK: udpin://0.0.0.0:{ep.remote[1]})" if ep.kind == "api" else ""
                parts.append(
                    f"{ep.kind.upper()} udp {ep.bind[0]}:{ep.bind[1]} -> {ep.remote[0]}:{ep.remote[1]}{hint}"
                )
            lines.append(f"sitl: {name} (system {eps[0].sysid}): " + ", ".join(parts))
        return lines

    async def _run_sim(self) -> None:
        loop = asyncio.get_running_loop()
        world = self.world
        dt = world.dt_s
        speed = self.speed_factor
        wall0 = loop.time()
        sim0 = world.t_s
        while True:
            now = loop.time()
            target = sim0 + (now - wall0) * speed
            behind = target - world.t_s
            if behind > MAX_CATCH_UP_S:
                # The host cannot keep up: slip instead of bursting (sim time stays smooth).
                self.overruns += 1
                if self.overruns in (1, 10, 100) or self.overruns % 1000 == 0:
                    log.warning("sitl: host too slow for %.1fx; slipped %d times", speed, self.overruns)
                sim0 = world.t_s
                wall0 = now
                target = world.t_s + dt
            n = int((target - world.t_s) / dt + 1e-9)
            for i in range(n):
                world.step()
                if i & 1:
                    # Let waiting datagrams in between ticks: asyncio hands a datagram protocol
                    # one packet per loop iteration, so a long batch would starve the sockets.
                    await asyncio.sleep(0)
            if n:
                for proto in self.udp:
                    proto.flush()
                self.sim._notify()
            next_wall = wall0 + (world.t_s + dt - sim0) / speed
            await asyncio.sleep(max(LOOP_PERIOD_S * 0.5, min(LOOP_PERIOD_S, next_wall - loop.time())))

    async def run(self, stop: asyncio.Event, on_ready: Callable[[], None] | None = None) -> None:
        """Serve until ``stop`` is set."""
        await self._open()
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [tg.create_task(self._run_sim(), name="sitl.sim")]
                for i, comp in enumerate(self.components):
                    name = getattr(comp, "__qualname__", f"component{i}")
                    tasks.append(
                        tg.create_task(_run_component(comp, self.sim), name=f"sitl.component.{name}")
                    )
                if on_ready is not None:
                    on_ready()
                tg.create_task(_stop_when(stop, tasks), name="sitl.stop")
        finally:
            self._close()
            self._log_counters()

    def _log_counters(self) -> None:
        for proto in self.udp:
            c = proto.counters
            log.info(
                "%s: datagrams in %d (bad %d), messages in %d, bad messages %d, out %d, send errors %d",
                proto.label,
                c["datagrams_in"],
                c["bad_datagrams"],
                c["messages_in"],
                c["bad_messages"],
                c["messages_out"],
                c["send_errors"],
            )
        for v in self.world.vehicles:
            c = v.autopilot.counters
            log.info(
                "%s autopilot: messages %d, handler errors %d, setpoints %d (refused %d)",
                v.name,
                c["messages_in"],
                c["handler_errors"],
                c["setpoints"],
                c["setpoints_refused"],
            )
        if self.overruns:
            log.info("sitl: slipped real time %d times", self.overruns)


async def _run_component(component: Component, sim: SimHandle) -> None:
    await component(sim)


async def _stop_when(stop: asyncio.Event, tasks: list[asyncio.Task[None]]) -> None:
    await stop.wait()
    for task in tasks:
        task.cancel()


def main(args: argparse.Namespace, components: Sequence[Component] = ()) -> int:
    """Entry point of ``sitl serve``; ``components`` are the hosting program's (see the module's doc)."""
    setup_logging(args.log_format, args.log_level)
    config = args.config if args.config is not None else project_root() / "config" / "sitl.toml"
    cfg = load_sitl_config(config)
    scenario = None
    if args.scenario is not None:
        scenario = load_scenario(find_scenario(str(args.scenario), Path(config).parent / "scenarios"))
    speed = args.speed if args.speed is not None else cfg.world.speed_factor
    if not (math.isfinite(speed) and 0 < speed <= 100):
        raise ConfigError("--speed", [f"must be in (0, 100] (got {speed})"])
    components = list(components)
    if not getattr(args, "no_camera", True):
        from sitl.render.camera_server import make_camera_component  # noqa: PLC0415 (renderer: heavy)

        components.append(make_camera_component(args.camera))
    if getattr(args, "autopilot", "builtin") == "px4":
        from sitl.px4.serve import serve as serve_px4  # noqa: PLC0415 (only for this backend)

        return serve_px4(
            cfg, scenario, speed_factor=speed, seed=getattr(args, "seed", None), components=components
        )
    server = Server(
        cfg, scenario, speed_factor=speed, seed=getattr(args, "seed", None), components=components
    )
    asyncio.run(_serve(server, scenario))
    return 0


async def _serve(server: Server, scenario: Scenario | None) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    def ready() -> None:
        for line in server.banner():
            print(line, flush=True)
        what = f"scenario {scenario.name}" if scenario is not None else "no scenario"
        print(
            f"sitl: running at {server.speed_factor:g}x real time ({what}, seed {server.world.seed}); "
            "Ctrl-C stops",
            flush=True,
        )

    try:
        await server.run(stop, on_ready=ready)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(sig)
    print("sitl: stopped", flush=True)


__all__ = ["BindError", "Component", "Server", "SimHandle", "main"]
