"""The MQTT client's edges: a session's tasks end even when one swallows a cancellation."""

from __future__ import annotations

import asyncio

import pytest

from companion.telemetry.mqtt_client import cancel_and_wait


async def swallows_first_cancel(woken: asyncio.Event, swallowed: list[int]) -> None:
    """A task after 3.10's ``wait_for`` swallowed its cancellation: it waits for work again."""
    try:
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        swallowed.append(1)
    await woken.wait()  # the publish loop's "wait for the next message"


async def test_a_task_that_swallowed_its_cancellation_still_ends() -> None:
    swallowed: list[int] = []
    never = asyncio.Event()
    stubborn = asyncio.create_task(swallows_first_cancel(never, swallowed))
    plain = asyncio.create_task(asyncio.sleep(3600))
    await asyncio.sleep(0)
    await asyncio.wait_for(cancel_and_wait([stubborn, plain]), 5)
    assert swallowed == [1]
    assert stubborn.cancelled()
    assert plain.cancelled()


async def test_a_plain_gather_after_cancel_would_wait_for_ever() -> None:
    """The failure cancel_and_wait exists for: one cancel() and a gather never return."""
    never = asyncio.Event()
    stubborn = asyncio.create_task(swallows_first_cancel(never, []))
    await asyncio.sleep(0)
    stubborn.cancel()
    with pytest.raises(asyncio.TimeoutError):
        await asyncio.wait_for(asyncio.shield(asyncio.gather(stubborn, return_exceptions=True)), 0.3)
    await cancel_and_wait([stubborn])
    assert stubborn.cancelled()


async def test_the_callers_cancellation_waits_for_its_tasks_then_is_raised() -> None:
    ended: list[str] = []

    async def slow_to_end() -> None:
        try:
            await asyncio.sleep(3600)
        finally:
            await asyncio.sleep(0.1)  # cleanup that takes a while (closing a socket)
            ended.append("child")

    child = asyncio.create_task(slow_to_end())
    await asyncio.sleep(0)
    caller = asyncio.create_task(cancel_and_wait([child]))
    await asyncio.sleep(0.01)
    caller.cancel()
    with pytest.raises(asyncio.CancelledError):
        await caller
    assert ended == ["child"]
    assert child.done()


async def test_an_error_a_task_raised_is_retrieved_not_logged_as_lost() -> None:
    async def fails() -> None:
        raise OSError("connection reset")

    task = asyncio.create_task(fails())
    await asyncio.sleep(0)
    await cancel_and_wait([task])
    assert isinstance(task.exception(), OSError)
