"""What the service uses from Python 3.11, on Python 3.10 too (JetPack 6 ships 3.10).

``TaskGroup`` and ``timeout`` come from the ``taskgroup`` backport, exception groups from ``exceptiongroup``,
``tomllib`` from ``tomli`` (the library it was taken from), ``Self`` from ``typing_extensions``; on 3.11+
these are the standard library's own. Code the drone runs imports them from here, never from
``asyncio`` or ``tomllib`` directly.
"""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):  # noqa: UP036 (the service supports 3.10; ruff checks as 3.11)
    import tomllib
    from asyncio import TaskGroup, timeout
    from builtins import BaseExceptionGroup, ExceptionGroup
    from enum import StrEnum
    from typing import Self
else:  # pragma: no cover - exercised by the Python 3.10 run of the unit tests
    from enum import Enum

    import tomli as tomllib
    from exceptiongroup import BaseExceptionGroup, ExceptionGroup
    from taskgroup import TaskGroup, timeout
    from typing_extensions import Self  # noqa: UP035 (typing.Self is 3.11+)

    class StrEnum(str, Enum):  # noqa: UP042 (enum.StrEnum is 3.11+)
        """``enum.StrEnum``: members are strings, ``str(member)`` is the value."""

        def __str__(self) -> str:
            return str(self.value)

        @staticmethod
        def _generate_next_value_(name: str, start: int, count: int, last_values: list[str]) -> str:
            return name.lower()


__all__ = ["BaseExceptionGroup", "ExceptionGroup", "Self", "StrEnum", "TaskGroup", "timeout", "tomllib"]
