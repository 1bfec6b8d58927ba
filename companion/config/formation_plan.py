"""Formation plans: where each follower flies in the leader's frame (``config/formations/*.toml``).

A plan is shared by every follower's service and by the simulator's harness: each service flies the slot
named by its ``vehicle_id`` and knows where the others should be, which is what keeps the leader's identity
apart from a neighbour's after GPS loss. Schema::

    schema_version = 1
    name = "v"
    description = "..."
    [[slots]]
    follower = "follower1"          # the follower's vehicle_id
    offset_m = [-4.0, -3.0, 0.0]    # its place in the leader's level heading frame: forward, right, down, m

Slots in front of the leader (``forward`` >= 0) or closer than 2 m are refused: the follower sees the
leader with a front camera and keeps ``safety.min_separation_m``.
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.kernel.config import Section, format_validation_error, read_toml
from companion.kernel.errors import ConfigError

PLAN_SCHEMA_VERSION = 1
#: Closest two slots (or a slot and the leader) may be, m.
MIN_SLOT_SPACING_M = 2.0


class Slot(Section):
    """One follower's place: ``offset_m`` in the leader's level heading frame (forward, right, down), m."""

    follower: str = Field(pattern=r"^[A-Za-z0-9_-]{1,32}$")
    offset_m: tuple[float, float, float]

    @field_validator("offset_m")
    @classmethod
    def _behind(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(math.isfinite(x) for x in v):
            raise ValueError("must be finite")
        if v[0] >= 0.0:
            raise ValueError("the slot must be behind the leader (forward < 0): the camera looks ahead")
        return v

    @property
    def range_h_m(self) -> float:
        return math.hypot(self.offset_m[0], self.offset_m[1])


class FormationPlan(Section):
    """A formation: one slot per follower."""

    schema_version: int = PLAN_SCHEMA_VERSION
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_-]{0,47}$")
    description: str = ""
    slots: tuple[Slot, ...] = Field(min_length=1, max_length=16)

    @model_validator(mode="after")
    def _apart(self) -> FormationPlan:
        names = [s.follower for s in self.slots]
        if len(set(names)) != len(names):
            raise ValueError("each follower may have one slot only")
        points = [(0.0, 0.0, 0.0), *(s.offset_m for s in self.slots)]
        for i, a in enumerate(points):
            for b in points[i + 1 :]:
                if math.dist(a, b) < MIN_SLOT_SPACING_M:
                    raise ValueError(f"slots {a} and {b} are closer than {MIN_SLOT_SPACING_M} m")
        return self

    def slot(self, follower: str) -> Slot:
        for s in self.slots:
            if s.follower == follower:
                return s
        raise KeyError(f"plan {self.name!r} has no slot for {follower!r} (has {', '.join(self.followers)})")

    @property
    def followers(self) -> tuple[str, ...]:
        return tuple(s.follower for s in self.slots)


def load_plan(path: Path) -> FormationPlan:
    """Read and validate a plan; every problem is one line of a :class:`ConfigError`."""
    data = read_toml(path)
    try:
        return FormationPlan.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path), format_validation_error(exc)) from None
