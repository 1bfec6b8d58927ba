"""The mission: formation law, safety limits, the state machine and the runner that ties them to a link.

Pure cores (``formation`` with ``geometry`` and ``static_pass``, ``safety``, ``machine`` with ``monitors``,
``offboard`` and ``states``) take time as an argument and do no I/O; the runner
(:mod:`companion.service.mission_runner`) is the thin asyncio edge.
"""
