"""When the signing relay may send the key (SETUP_SIGNING): a one-shot step, refused whenever in doubt.

The key crosses the link in clear, so it goes only to an autopilot that is plainly ours and plainly
without a key: one address alone claims it, its heartbeats say disarmed, and no frame signed with our
key has arrived from anywhere (an autopilot that signs but is behind, after a boot, already has it). On a
listening UDP link any host can claim the autopilot's system id, so there the key goes only to a sender on
the board itself (loopback: a simulator or SITL), heard alone for ``PROVISION_LISTEN_S``; provision a
networked autopilot over serial or udpout, which reach one known address only. Once the autopilot signs,
``PROVISIONED_FILE`` in ``service.state_dir`` ends provisioning for good.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from companion.vehicle.relay_transports import SERIAL, Addr, where

#: Written once the autopilot signs with our key: from then on the key is never sent again.
PROVISIONED_FILE = "mavlink-signing-provisioned"
#: Provisioning on ``udpin``: one address must have claimed the autopilot alone for this long, s.
PROVISION_LISTEN_S = 5.0


@dataclass(frozen=True, slots=True)
class ProvisionScene:
    """What the relay has heard, for :func:`provision_refusal`."""

    #: Our autopilot's system id.
    target: int
    #: The link's scheme: udpin, udpout or serial.
    scheme: str
    #: A frame signed with our key arrived from somewhere.
    key_seen: bool
    #: Every address that claimed our autopilot unsigned, with when it was first heard (monotonic s).
    claimants: dict[Addr, float]
    #: The addresses heard unsigned just now, with whether their heartbeat says armed.
    fresh: dict[Addr, bool]


def provision_refusal(scene: ProvisionScene, now_s: float) -> str | None:
    """Why the key must not go at ``now_s`` (monotonic s); None: it may go to the one fresh address."""
    target = scene.target
    if scene.key_seen:
        return f"a frame signed with our key has arrived: system {target} already has it"
    if len(scene.claimants) > 1 or len(scene.fresh) != 1:
        heard = ", ".join(where(a) for a in scene.claimants)
        return f"system {target} claimed unsigned from more than one address ({heard})"
    addr, armed = next(iter(scene.fresh.items()))
    if armed:
        return f"autopilot system {target} is armed, unsigned: the key goes only while disarmed"
    if scene.scheme == "udpin" and addr != SERIAL:
        if not addr[0].startswith("127."):
            return (
                f"autopilot system {target} is at {where(addr)} on a listening UDP link, where any host "
                "can claim it: provision it over serial or udpout"
            )
        if now_s - scene.claimants.get(addr, now_s) < PROVISION_LISTEN_S:
            return f"listening {PROVISION_LISTEN_S:g} s for a second claimant before sending the key"
    return None


def write_marker(path: Path, key_id: str) -> None:
    """Provisioning is done: ``path`` holds the key's id (blocking: call off the event loop)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"{key_id}\n")
