"""One PX4 SITL process (SIH physics inside), in a temporary working folder that is removed when it stops.

PX4 numbers everything by its instance ``i``: the offboard API link is bound to UDP ``14580 + i`` and
sends to ``14540 + i``, the GCS link is bound to ``18570 + i``, SIH's display link is bound to
``19450 + i`` and sends to ``19410 + i``, and ``px4-<module> --instance i`` talks to its shell through
``/tmp/px4-sock-i``. :func:`free_instance_base` finds instance numbers whose ports are all free, so two
runs side by side never share one.

A PX4 build keeps ``bin/px4`` beside ``etc/`` (``build/px4_sitl_default``); its ``px4-<module>`` shell
commands are links to ``px4`` that the startup script calls through ``PATH``. Each instance gets its own
``bin/`` of such links, so a build whose links were copied as plain files (a read-only or archived copy)
runs as well.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from companion.kernel.children import die_with_parent
from companion.kernel.errors import CompanionError

log = logging.getLogger(__name__)

#: The highest instance number with its own API remote port (PX4 shares 14549 from instance 10 on).
MAX_INSTANCE = 9
#: Wall time a PX4 shell command may take, s.
SHELL_TIMEOUT_S = 10.0


class Px4NotFoundError(CompanionError):
    """The PX4 SITL build named in the configuration is missing or is not one."""

    exit_code = 2


class Px4StartError(CompanionError):
    """A PX4 instance did not start, or died."""

    exit_code = 1


@dataclass(frozen=True, slots=True)
class Px4Build:
    """A PX4 SITL build: the ``px4`` binary, and the ``etc/`` folder (ROMFS) beside its ``bin/``."""

    binary: Path
    etc_dir: Path

    @classmethod
    def locate(cls, binary: str) -> Px4Build:
        """The build whose binary is ``binary`` (a path, or a name on ``PATH``); one line if it is not one."""
        hint = "set [px4] binary in the simulator config or SITL_PX4__BINARY to a PX4 SITL build's bin/px4"
        found = shutil.which(binary) if os.sep not in binary else binary
        if not found:
            raise Px4NotFoundError(f"PX4 SITL binary {binary!r} not found on PATH; {hint}")
        path = Path(found).expanduser().resolve()
        if not path.is_file() or not os.access(path, os.X_OK):
            raise Px4NotFoundError(f"PX4 SITL binary {path} is not an executable file; {hint}")
        etc = path.parent.parent / "etc"
        if not (etc / "init.d-posix" / "rcS").is_file():
            raise Px4NotFoundError(f"{path} is not a PX4 SITL build: no {etc}/init.d-posix/rcS beside it")
        return cls(path, etc)

    def modules(self) -> list[str]:
        """The ``px4-<module>`` command names the build ships beside its binary."""
        return sorted(
            p.name for p in self.binary.parent.iterdir() if p.name.startswith("px4-") and p.suffix != ".sh"
        )


@dataclass(frozen=True, slots=True)
class Px4Ports:
    """The UDP ports of PX4 instance ``i`` (PX4's own numbering in ``px4-rc.mavlink``)."""

    instance: int

    @property
    def api_local(self) -> int:
        return 14580 + self.instance

    @property
    def api_remote(self) -> int:
        """Where the offboard API link sends: MAVSDK's ``udpin://0.0.0.0:<this>``."""
        return 14540 + self.instance

    @property
    def sih_local(self) -> int:
        return 19450 + self.instance

    @property
    def sih_remote(self) -> int:
        """Where SIH's display link sends (ground truth): the simulator listens here."""
        return 19410 + self.instance

    def all(self) -> tuple[int, ...]:
        i = self.instance
        return (
            self.api_local,
            self.api_remote,
            18570 + i,
            14280 + i,
            13030 + i,
            self.sih_local,
            self.sih_remote,
        )


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))  # noqa: S104 (PX4 and MAVSDK bind all interfaces)
        except OSError:
            return False
    return True


def free_instance_base(count: int) -> int:
    """The lowest instance number ``b`` such that instances ``b .. b + count - 1`` have every port free."""
    for base in range(MAX_INSTANCE + 2 - count):
        if all(_udp_free(p) for i in range(base, base + count) for p in Px4Ports(i).all()):
            return base
    raise Px4StartError(f"no {count} PX4 instance numbers with free UDP ports (14540-14549 are taken)")


def param_env(params: dict[str, float]) -> dict[str, str]:
    """``PX4_PARAM_<NAME>`` variables (PX4's startup script sets each one) for ``params``."""
    out = {}
    for name, value in params.items():
        if not math.isfinite(value):
            raise Px4StartError(f"PX4 parameter {name} = {value} is not finite")
        out[f"PX4_PARAM_{name}"] = repr(int(value)) if float(value).is_integer() else repr(float(value))
    return out


class Px4Instance:
    """One PX4 SITL process in a working folder of its own.

    Args:
        build: The PX4 build to run.
        instance: PX4's instance number (ports, shell socket).
        name: The vehicle's name (logs).
        params: Parameters set at start (``MAV_SYS_ID``, SIH's home and wind, ...).
        speed_factor: ``PX4_SIM_SPEED_FACTOR`` (SIH runs lockstep, that many times real time).
        model: SIH airframe (``PX4_SIM_MODEL``).
    """

    def __init__(
        self,
        build: Px4Build,
        instance: int,
        name: str,
        params: dict[str, float],
        *,
        speed_factor: float = 1.0,
        model: str = "sihsim_quadx",
    ) -> None:
        self.build = build
        self.instance = instance
        self.name = name
        self.params = dict(params)
        self.speed_factor = speed_factor
        self.model = model
        self.ports = Px4Ports(instance)
        self.work_dir: Path | None = None
        self.proc: subprocess.Popen[bytes] | None = None
        self._env: dict[str, str] = {}

    @property
    def log_path(self) -> Path | None:
        return None if self.work_dir is None else self.work_dir / "px4.log"

    def start(self) -> None:
        """Make the working folder and start PX4 (returns at once; PX4 boots in the background)."""
        work = Path(tempfile.mkdtemp(prefix=f"wingman-px4-{self.name}-"))
        self.work_dir = work
        bin_dir = work / "bin"
        bin_dir.mkdir()
        (bin_dir / "px4").symlink_to(self.build.binary)
        for module in self.build.modules():
            (bin_dir / module).symlink_to(self.build.binary)
        alias = self.build.binary.parent / "px4-alias.sh"
        if alias.is_file():
            (bin_dir / alias.name).symlink_to(alias)
        self._env = {
            **os.environ,
            "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
            "PX4_SIM_MODEL": self.model,
            "PX4_SIMULATOR": "sihsim",
            **param_env(self.params),
        }
        if self.speed_factor != 1.0:
            self._env["PX4_SIM_SPEED_FACTOR"] = f"{self.speed_factor:g}"
        args = [
            str(bin_dir / "px4"),
            "-i",
            str(self.instance),
            "-d",
            str(self.build.etc_dir),
            "-w",
            str(work / "rootfs"),
        ]
        with (work / "px4.log").open("wb") as out:
            self.proc = subprocess.Popen(
                args,
                cwd=work,
                env=self._env,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # Ctrl-C goes to the simulator, which stops PX4 in order
                preexec_fn=die_with_parent,  # noqa: PLW1509 (one prctl call, no locks taken)
            )
        log.info("px4 %s: instance %d (pid %d) in %s", self.name, self.instance, self.proc.pid, work)

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def tail(self, n: int = 2000) -> str:
        path = self.log_path
        if path is None or not path.exists():
            return ""
        return path.read_text(errors="replace")[-n:]

    async def shell(self, *command: str) -> None:
        """Run one PX4 shell command (``px4-<module> --instance i ...``); its output goes to PX4's log."""
        if self.work_dir is None:
            raise Px4StartError(f"px4 {self.name} was never started")
        module, *args = command
        proc = await asyncio.create_subprocess_exec(
            str(self.work_dir / "bin" / f"px4-{module}"),
            "--instance",
            str(self.instance),
            *args,
            cwd=self.work_dir,
            env=self._env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            rc = await asyncio.wait_for(proc.wait(), SHELL_TIMEOUT_S)
        except TimeoutError:
            proc.kill()
            await proc.wait()
            raise Px4StartError(f"px4 {self.name}: '{' '.join(command)}' did not return") from None
        if rc != 0:
            log.warning("px4 %s: '%s' exited %d", self.name, " ".join(command), rc)

    def flight_logs(self) -> list[Path]:
        """The ULog files PX4 wrote so far, oldest first."""
        if self.work_dir is None:
            return []
        return sorted((self.work_dir / "rootfs" / "log").glob("*/*.ulg"))

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM to PX4's process group, then SIGKILL after ``timeout_s``. Idempotent."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)

    def remove(self, keep_logs_in: Path | None = None) -> list[Path]:
        """Stop, copy the flight logs into ``keep_logs_in`` (if given), delete the working folder.

        Returns the copied logs' paths.
        """
        self.stop()
        kept: list[Path] = []
        if keep_logs_in is not None:
            keep_logs_in.mkdir(parents=True, exist_ok=True)
            for i, ulg in enumerate(self.flight_logs()):
                dest = keep_logs_in / f"px4-{self.name}-{i}.ulg"
                shutil.copyfile(ulg, dest)
                kept.append(dest)
            if self.log_path is not None and self.log_path.exists():
                shutil.copyfile(self.log_path, keep_logs_in / f"px4-{self.name}.log")
        if self.work_dir is not None:
            shutil.rmtree(self.work_dir, ignore_errors=True)
            self.work_dir = None
        return kept
