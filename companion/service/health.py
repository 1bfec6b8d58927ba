"""``HealthBoard``: every component reports here; the status endpoint, MQTT and the systemd watchdog read it.

A component *beats* while its loop is alive and says whether it is ok. A critical component whose beats
stop for longer than its ``stale_after_s`` is considered hung: the watchdog stops pinging systemd.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.kernel.clock import Clock


@dataclass(slots=True)
class _Entry:
    critical: bool
    stale_after_s: float | None
    ok: bool = False
    detail: str = "starting"
    last_beat_s: float | None = None
    restarts: int = 0
    failures: int = 0


@dataclass(frozen=True, slots=True)
class ComponentHealth:
    """One component's health at a given time."""

    name: str
    critical: bool
    ok: bool
    alive: bool
    detail: str
    #: Seconds since the last beat, None before the first.
    age_s: float | None
    restarts: int
    failures: int

    def to_json(self) -> dict[str, object]:
        return {
            "name": self.name,
            "critical": self.critical,
            "ok": self.ok,
            "alive": self.alive,
            "detail": self.detail,
            "age_s": None if self.age_s is None else round(self.age_s, 3),
            "restarts": self.restarts,
            "failures": self.failures,
        }


class HealthBoard:
    """Per-component liveness and status, evaluated against a clock when read."""

    def __init__(self, clock: Clock) -> None:
        self._clock = clock
        self._entries: dict[str, _Entry] = {}

    def register(self, name: str, *, critical: bool, stale_after_s: float | None = None) -> None:
        """Declare a component. ``stale_after_s``: beats further apart than this mean it is hung."""
        self._entries[name] = _Entry(critical=critical, stale_after_s=stale_after_s)

    def beat(self, name: str, *, ok: bool = True, detail: str = "") -> None:
        """The component's loop is alive; ``ok`` says whether it is doing its job."""
        e = self._entry(name)
        e.last_beat_s = self._clock.now_s()
        e.ok = ok
        e.detail = detail or ("ok" if ok else "degraded")

    def fail(self, name: str, detail: str) -> None:
        """The component failed (its supervisor will restart it, or the service will stop)."""
        e = self._entry(name)
        e.ok = False
        e.failures += 1
        e.detail = detail

    def restarted(self, name: str) -> None:
        self._entry(name).restarts += 1

    def component(self, name: str) -> ComponentHealth:
        return self._evaluate(name, self._entry(name), self._clock.now_s())

    def snapshot(self) -> list[ComponentHealth]:
        """Every component, in registration order."""
        now_s = self._clock.now_s()
        return [self._evaluate(n, e, now_s) for n, e in self._entries.items()]

    def critical_alive(self) -> bool:
        """True when every critical component has beaten within its ``stale_after_s``."""
        return all(c.alive for c in self.snapshot() if c.critical)

    def all_ok(self) -> bool:
        return all(c.ok for c in self.snapshot())

    def _entry(self, name: str) -> _Entry:
        try:
            return self._entries[name]
        except KeyError:
            raise KeyError(f"component {name!r} is not registered on the health board") from None

    @staticmethod
    def _evaluate(name: str, e: _Entry, now_s: float) -> ComponentHealth:
        age_s = None if e.last_beat_s is None else max(0.0, now_s - e.last_beat_s)
        if e.stale_after_s is None:
            alive = e.last_beat_s is not None
        else:
            alive = age_s is not None and age_s <= e.stale_after_s
        detail = e.detail
        if age_s is not None and not alive:
            detail = f"no beat for {age_s:.1f} s ({e.detail})"
        return ComponentHealth(
            name=name,
            critical=e.critical,
            ok=e.ok and alive,
            alive=alive,
            detail=detail,
            age_s=age_s,
            restarts=e.restarts,
            failures=e.failures,
        )
