"""The simulator signs as PX4 does, on the wire: ``sitl serve`` as a process, a pymavlink peer over UDP.

The same steps PX4 SITL was tried with (../shared/px4-sitl/README.md): an unsigned read is answered
until SETUP_SIGNING; then unsigned requests go unanswered, signed ones are answered and the answers are
signed, an unsigned land from another system does nothing, and SETUP_SIGNING is refused while armed.
"""

from __future__ import annotations

import asyncio
import secrets

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from tests.integration.sitl_process import sitl_serve
from tests.signing_probe import MavPeer, send_unsigned_land

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]

FOLLOWER = 2
PARAM = "MPC_XY_VEL_MAX"


async def test_the_simulator_takes_a_key_while_disarmed_and_then_drops_unsigned_input() -> None:
    key = secrets.token_bytes(32)
    with sitl_serve(speed=1.0) as sim:
        addr = ("127.0.0.1", sim.ports.api_local + 1)  # the follower's API port, as PX4's 14581
        plain = await MavPeer.open(addr)
        signed = await MavPeer.open(addr, key=key)
        other_key = await MavPeer.open(addr, key=secrets.token_bytes(32))
        try:
            assert await plain.param_answered(FOLLOWER, PARAM)
            assert plain.last_signed("PARAM_VALUE") is False

            plain.setup_signing(FOLLOWER, key)
            await asyncio.sleep(0.3)
            assert not await plain.param_answered(FOLLOWER, PARAM), "unsigned after the key: dropped"
            assert not await other_key.param_answered(FOLLOWER, PARAM), "signed with another key: dropped"
            assert await signed.param_answered(FOLLOWER, PARAM)
            assert signed.last_signed("PARAM_VALUE") is True
            await asyncio.sleep(1.5)
            assert plain.signed_from.get(FOLLOWER, 0) > 0  # its streams are signed now
            assert plain.last_signed("HEARTBEAT") is True

            # An unsigned land from another system: no answer, nothing happens.
            send_unsigned_land(addr, FOLLOWER)
            await asyncio.sleep(0.5)
            acks = [m for m in plain.received + signed.received if m.get_type() == "COMMAND_ACK"]
            assert not [a for a in acks if a.command == mavlink2.MAV_CMD_NAV_LAND]

            # Armed (once its estimator is ready: arming waits for health), a new key is refused, even signed.
            for _ in range(40):
                start = len(signed.received)
                signed.send(
                    mavlink2.MAVLink_command_long_message(
                        FOLLOWER, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
                    )
                )
                await asyncio.sleep(0.5)
                results = [
                    m.result
                    for m in signed.received[start:]
                    if m.get_type() == "COMMAND_ACK" and m.command == mavlink2.MAV_CMD_COMPONENT_ARM_DISARM
                ]
                if mavlink2.MAV_RESULT_ACCEPTED in results:
                    break
            else:
                pytest.fail("the follower never armed")
            signed.setup_signing(FOLLOWER, secrets.token_bytes(32))
            await asyncio.sleep(0.3)
            assert await signed.param_answered(FOLLOWER, PARAM), "the old key still holds"
        finally:
            for p in (plain, signed, other_key):
                p.close()
    log = "\n".join(sim.output)
    assert "MAVLink signing key accepted" in log
    assert "SETUP_SIGNING refused while armed" in log
    assert "Traceback" not in log
