"""The mission: formation law, safety limits, the state machine and the runner that ties them to a link.

Pure cores (``formation``, ``safety``, ``machine``) take time as an argument and do no I/O; ``runner`` is the
thin asyncio edge.
"""
