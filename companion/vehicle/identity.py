"""Which autopilot on a link is ours: the service commands one system id and never the leader's.

Pure: the link hands in the system ids it has heard from autopilots (component 1 with a HEARTBEAT) and how
long it has listened; the verdict says which one to fly, to keep listening, or to refuse the link.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Verdict:
    """``system_id`` to fly (None: none yet); ``refusal`` set when the link must be given up, in one line."""

    system_id: int | None = None
    refusal: str | None = None
    #: What is heard so far, for a waiting log line.
    waiting: str = ""


def choose_autopilot(
    heard: Iterable[int],
    wanted: int,
    *,
    leader: int | None,
    listened_s: float,
    patience_s: float,
    url: str,
) -> Verdict:
    """Pick the autopilot to fly among the system ids ``heard``.

    Args:
        heard: system ids of the autopilots heard on the link so far.
        wanted: ``link.system_id`` (0: the first that is not the leader's).
        leader: the leader's system id (``leader.mavlink_system_id``); never chosen.
        listened_s: how long the link has listened, s.
        patience_s: after this long hearing only systems that are not ours, refuse the link.
        url: the link, for the messages.
    """
    ids = sorted(set(heard))
    if wanted != 0 and wanted in ids and wanted != leader:
        return Verdict(system_id=wanted)
    if wanted == 0:
        others = [i for i in ids if i != leader]
        if others:
            return Verdict(system_id=others[0])
    if not ids:
        return Verdict(waiting=f"no autopilot on {url} yet")
    target = f"system {wanted}" if wanted else "an autopilot that is not the leader's"
    names = ", ".join(f"{i} (the leader)" if i == leader else str(i) for i in ids)
    if listened_s >= patience_s:
        return Verdict(
            refusal=f"{url} carries autopilot system {names}, not {target}: refusing to command it "
            "(set link.url to the follower's own autopilot, or link.system_id)"
        )
    return Verdict(waiting=f"heard system {names} on {url}, waiting for {target}")
