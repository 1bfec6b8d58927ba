"""A stand-in for the renderer's camera server: an in-process ``sitl serve`` component, passed in.

``python -m tests.integration.sitl_component serve ...`` is ``sitl`` hosting :func:`report_truth`, as the
lab's :mod:`companion.lab.evaluation.sitl_host` hosts its components.
"""

from __future__ import annotations

import asyncio

from sitl.cli import main
from sitl.serve.server import SimHandle


async def report_truth(sim: SimHandle) -> None:
    """Print every vehicle's true position at sim times 1, 2, 3 s, then idle until cancelled."""
    for t in (1.0, 2.0, 3.0):
        await sim.wait_until(t)
        for name in sim.names:
            p = sim.truth(name).p_ned_m
            print(f"component: t={sim.t_s:.3f} {name} n={p[0]:.2f} e={p[1]:.2f} d={p[2]:.3f}", flush=True)
    await asyncio.Event().wait()  # until serve cancels us


if __name__ == "__main__":
    raise SystemExit(main(components=(report_truth,)))
