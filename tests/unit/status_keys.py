"""Which keys ``companion status``'s page reads that the status JSON it was given does not have."""

from __future__ import annotations

from typing import Any

from companion.commands.status import render_status


class _Reads(dict[str, Any]):
    """A JSON object that notes each key read from it (nested objects too) that it does not hold."""

    def __init__(self, data: dict[str, Any], path: str, missing: set[str]) -> None:
        super().__init__(data)
        self._path, self._missing = path, missing

    def _wrap(self, key: str, value: Any) -> Any:
        return _Reads(value, f"{self._path}{key}.", self._missing) if isinstance(value, dict) else value

    def get(self, key: str, default: Any = None) -> Any:  # type: ignore[override]
        if key not in self:
            self._missing.add(self._path + key)
        return self._wrap(key, super().get(key, default))

    def __getitem__(self, key: str) -> Any:
        if key not in self:
            self._missing.add(self._path + key)
        return self._wrap(key, super().__getitem__(key))

    def items(self) -> Any:  # type: ignore[override]
        return [(k, self._wrap(k, v)) for k, v in super().items()]


def keys_the_page_misses(status: dict[str, Any]) -> tuple[str, set[str]]:
    """The page rendered from ``status``, and the keys it read that ``status`` lacks (dotted paths)."""
    missing: set[str] = set()
    text = render_status(_Reads(status, "", missing))
    return text, missing
