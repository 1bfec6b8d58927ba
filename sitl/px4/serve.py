"""``sitl serve --autopilot px4``: the scenario on real PX4 SITL, with the components of ``sitl serve``."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Sequence
from pathlib import Path

from sitl.config import SitlConfig
from sitl.px4.instance import Px4Build
from sitl.px4.world import Px4World
from sitl.serve.server import Component
from sitl.world.scenario import Scenario


def banner(world: Px4World) -> list[str]:
    """Where each vehicle talks, as ``sitl serve`` prints it."""
    lines = []
    for v in world.vehicles:
        p = v.instance.ports
        lines.append(
            f"sitl: {v.name} (system {v.sysid}): PX4 instance {p.instance}, API udp 0.0.0.0:{p.api_local} -> "
            f"127.0.0.1:{p.api_remote} (MAVSDK: udpin://0.0.0.0:{p.api_remote})"
        )
    return lines


def serve(
    cfg: SitlConfig,
    scenario: Scenario | None,
    *,
    speed_factor: float,
    seed: int | None,
    components: Sequence[Component],
) -> int:
    """Run the PX4 world until Ctrl-C or SIGTERM; every PX4 is stopped and its folder removed on exit."""
    build = Px4Build.locate(cfg.px4.binary)
    log_dir = Path(cfg.px4.log_dir) if cfg.px4.log_dir else None
    world = Px4World(cfg, scenario, build, speed_factor=speed_factor, seed=seed, log_dir=log_dir)
    asyncio.run(_serve(world, components))
    return 0


async def _serve(world: Px4World, components: Sequence[Component]) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    def ready() -> None:
        for line in banner(world):
            print(line, flush=True)
        scenario = world.scenario
        what = f"scenario {scenario.name}" if scenario is not None else "no scenario"
        print(
            f"sitl: running PX4 ({world.vehicles[0].instance.build.binary}) at {world.speed_factor:g}x "
            f"real time ({what}, seed {world.seed}); Ctrl-C stops",
            flush=True,
        )

    try:
        await world.run(stop, components, on_ready=ready)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(sig)
        for path in world.flight_logs:
            print(f"sitl: PX4 flight log {path}", flush=True)
    print("sitl: stopped", flush=True)
