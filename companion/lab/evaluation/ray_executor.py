"""Seeded campaigns on a Ray cluster (``companion sim --seeds A-B --executor ray``).

The driver submits one Ray task per seed (one CPU, the lockstep harness) to a Ray it starts on the loopback
address, or to a cluster it joins (``--ray-address``). A worker flies its run in a scratch folder and returns
the folder's files; the driver writes them under ``--out`` as each run arrives (``ray.wait``), so nothing
needs a shared file system and a campaign that stops keeps every run that arrived (``--resume`` skips them).

A task whose worker dies, or whose run raises, is retried :data:`MAX_RETRIES` time(s); a run that fails on
every attempt is listed in the summary's ``failed`` with its error line, and its whole error is written to
its folder's ``sim.log``. The summary is rebuilt from the seeds' reports at the end, as the local pool does.

Ray is optional (``pip install '.[cluster]'``) and imported only here, when a campaign asks for it.
"""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import time
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

from companion.kernel.errors import ConfigError
from companion.lab.evaluation.campaign import RunSpec, SimError, run_one
from companion.lab.evaluation.campaign_summary import write_campaign_summary
from companion.lab.evaluation.progress import StatusLine, progress_text

log = logging.getLogger(__name__)

#: Attempts after the first, for a lost worker or a run that raised.
MAX_RETRIES = 1
#: Paths never shipped with ``--ray-ship`` (besides what ``.gitignore`` excludes, which Ray honours).
SHIP_EXCLUDES = ("/runs/", "/data/", "/.venv/", "/.git/", "/.mypy_cache/", "/.ruff_cache/")


@dataclass(frozen=True, slots=True)
class RayOptions:
    """Where the tasks run."""

    #: A running cluster to join (``HOST:PORT`` or ``ray://HOST:PORT``); None starts a local Ray.
    address: str | None = None
    #: CPUs of a local Ray (one run each); a joined cluster has its own.
    local_cpus: int = 2
    #: Ship this checkout to the workers as Ray's runtime environment ``working_dir``.
    ship: bool = False
    #: Environment variables of a local Ray's workers (the checkout on ``PYTHONPATH``).
    local_env: Mapping[str, str] = field(default_factory=dict)


class RunFailedError(Exception):
    """A run raised on its worker: ``TypeName: message`` on the first line, then the traceback.

    Carried as text because not every exception survives pickling back to the driver (one whose
    ``__init__`` takes other arguments than its message, as :class:`ConfigError`'s does, does not).
    """


def run_seed(spec: RunSpec) -> dict[str, bytes]:
    """One run, on a worker: flown in a scratch folder; the folder's files (relative path -> bytes)."""
    try:
        return _run_seed(spec)
    except Exception as exc:
        first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), "(no message)")
        raise RunFailedError(f"{type(exc).__name__}: {first}\n{traceback.format_exc()}") from None


def _run_seed(spec: RunSpec) -> dict[str, bytes]:
    with tempfile.TemporaryDirectory(prefix="wingman-run-") as tmp:
        folder = Path(tmp) / spec.out_dir.name
        folder.mkdir()
        handler = logging.FileHandler(folder / "sim.log")
        handler.setLevel(logging.WARNING)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root = logging.getLogger()
        root.addHandler(handler)
        try:
            run_one(replace(spec, out_dir=folder, plots=False))
        finally:
            root.removeHandler(handler)
            handler.close()
        return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def error_line(exc: BaseException) -> str:
    """The one line a summary shows for a failed task: the run's own exception when there is one."""
    cause = getattr(exc, "cause", None)
    err = cause if isinstance(cause, BaseException) else exc
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    first = lines[0] if lines else "(no message)"
    return first if isinstance(err, RunFailedError) else f"{type(err).__name__}: {first}"


def write_run_files(out_dir: Path, files: Mapping[str, bytes]) -> None:
    """A finished run's files into its folder; ``report.json`` last, so its presence means a whole run."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in sorted(files, key=lambda n: n == "report.json"):
        target = out_dir / name
        if out_dir.resolve() not in target.resolve().parents:
            raise SimError(f"a worker returned a file outside its run folder: {name!r}")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(target.name + ".part")
        tmp.write_bytes(files[name])
        tmp.replace(target)


#: Ray's switch for a single machine (its default on macOS and Windows): every Ray process binds and
#: advertises 127.0.0.1 instead of the routable address. Read when ``ray`` is imported.
LOOPBACK_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}


def _import_ray(*, loopback: bool) -> Any:
    if loopback:
        os.environ.update(LOOPBACK_ENV)  # before the import, and inherited by the processes Ray starts
    try:
        import ray  # noqa: PLC0415 (optional: the cluster extra)
    except ImportError:
        raise ConfigError(
            "--executor ray", ["Ray is not installed here (pip install '.[cluster]')"]
        ) from None
    return ray


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in one line when a ``HOST:PORT`` cluster address refuses a connection (Ray would keep trying)."""
    host, sep, port = address.rpartition(":")
    if address.startswith("ray://") or not sep or not port.isdigit():
        return  # Ray client addresses and the forms Ray resolves itself are left to Ray
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise SimError(f"--ray-address {address}: no Ray head answers there ({exc})") from None


def _init(ray: Any, options: RayOptions) -> None:
    runtime_env: dict[str, Any] = {}
    if options.ship:
        from companion.lab.evaluation.setup import REPO  # noqa: PLC0415

        runtime_env["working_dir"] = str(REPO)
        runtime_env["excludes"] = list(SHIP_EXCLUDES)
    common: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}
    if options.address is None:
        if options.local_env:
            runtime_env["env_vars"] = dict(options.local_env)
        # A single-node Ray on the loopback address only (LOOPBACK_ENV): nothing else can reach it. Its
        # workers run at the local pool's priority: Ray's default (nice 15) let every other process on a
        # shared machine go first, and the same runs took 30 % longer beside a busy one.
        ray.init(
            address="local",
            num_cpus=max(1, options.local_cpus),
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            _system_config={"worker_niceness": 0},
            runtime_env=runtime_env or None,
            **common,
        )
    else:
        _check_reachable(options.address)
        ray.init(address=options.address, runtime_env=runtime_env or None, **common)


def run_campaign(
    specs: Sequence[RunSpec],
    out_dir: Path,
    *,
    options: RayOptions,
    stream: TextIO,
    already_done: Sequence[RunSpec] = (),
) -> dict[str, Any]:
    """Run ``specs`` as Ray tasks, write each run as it arrives, then the summary; return the summary.

    ``already_done``: a resumed campaign's seeds whose reports are kept (in the summary, not run).
    Raises :class:`SimError` after writing the summary when a run failed on every attempt.
    """
    for s in specs:
        if s.harness != "lockstep":
            raise ConfigError("--executor ray", ["runs the lockstep harness only (--harness lockstep)"])
    if not specs:  # every seed resumed: the summary alone
        return write_campaign_summary(
            already_done, out_dir, failed=[], wall_s=0.0, executor="ray", resumed=len(already_done)
        )
    ray = _import_ray(loopback=options.address is None)
    out_dir.mkdir(parents=True, exist_ok=True)
    for s in specs:
        s.out_dir.mkdir(parents=True, exist_ok=True)
        (s.out_dir / "report.json").unlink(missing_ok=True)  # a failed rerun leaves no stale report
    wall0 = time.perf_counter()  # the campaign's wall time includes starting or joining Ray
    try:
        _init(ray, options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = options.address or "a local Ray"
        raise SimError(f"cannot start or join Ray ({where}): {error_line(exc)}") from None
    line = StatusLine(stream, tty=stream.isatty())
    failed: list[str] = []
    done = 0
    t0_s = time.monotonic()
    pending: list[Any] = []
    try:
        task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=True)(run_seed)
        by_ref = {task.remote(s): s for s in specs}
        pending = list(by_ref)
        cpus = int(ray.cluster_resources().get("CPU", 0))
        while pending:
            # Whatever finished within a second: one call a second, however many runs are queued.
            ready, pending = ray.wait(pending, num_returns=len(pending), timeout=1.0)
            for ref in ready:
                spec = by_ref.pop(ref)
                done += 1
                try:
                    files = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    failed.append(f"{spec.out_dir.name}: {error_line(exc)}")
                    (spec.out_dir / "sim.log").write_text(f"{exc}\n")
                    log.warning("%s failed: %s", spec.out_dir.name, error_line(exc))
                else:
                    write_run_files(spec.out_dir, files)
            in_flight = [f"{len(pending)} to go on {cpus} CPUs"] if pending else []
            text = progress_text(
                done, len(failed), len(specs), in_flight, time.monotonic() - t0_s, label="sim[ray]"
            )
            line.write(text, force=bool(ready) and not pending)
    finally:
        line.close()
        for ref in pending:
            ray.cancel(ref)
        ray.shutdown()
    wall_s = time.perf_counter() - wall0
    summary = write_campaign_summary(
        [*already_done, *specs],
        out_dir,
        failed=failed,
        wall_s=wall_s,
        executor="ray" if options.address is None else f"ray at {options.address}",
        resumed=len(already_done),
    )
    if failed:
        raise SimError("runs without a report: " + "; ".join(failed))
    return summary
