"""Hostile MAVLink for tests: well-formed messages with absurd values, and broken datagrams."""

from __future__ import annotations

import math
import random
from collections.abc import Iterator, Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink


def random_message(rng: random.Random, classes: Sequence[Any] | None = None) -> Any:
    """A well-formed message of a random common type with random (often absurd) field values."""
    cls = rng.choice(list(classes or mavlink.mavlink_map.values()))
    args = []
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))  # wire order
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):  # constructor order
        n = lengths[name]
        if ftype == "char":
            args.append(bytes(rng.randrange(256) for _ in range(rng.randrange(n + 1))))
            continue
        if ftype in ("float", "double"):
            pick = [math.nan, math.inf, -math.inf, 0.0, 1e30, -1e30, rng.uniform(-1e4, 1e4)]
            val: Any = lambda pick=pick: rng.choice(pick)  # noqa: E731
        else:
            bits = int(ftype.rstrip("_t").lstrip("u").removeprefix("int") or 8)
            lo, hi = (0, 2**bits - 1) if ftype.startswith("u") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
            if name in ("target_system",):
                lo, hi = 0, 3
            val = lambda lo=lo, hi=hi: rng.randint(lo, hi)  # noqa: E731
        args.append([val() for _ in range(n)] if n else val())
    return cls(*args)


def datagrams(rng: random.Random, count: int) -> Iterator[bytes]:
    packer = mavlink.MAVLink(None, srcSystem=200, srcComponent=1)
    for _ in range(count):
        kind = rng.random()
        if kind < 0.3:
            yield bytes(rng.randrange(256) for _ in range(rng.randrange(0, 300)))
            continue
        try:
            frame = bytearray(random_message(rng).pack(packer, force_mavlink1=rng.random() < 0.1))
        except Exception:  # a random value pymavlink itself cannot pack: send junk instead
            yield bytes(rng.randrange(256) for _ in range(40))
            continue
        if kind < 0.5:
            frame[-1] ^= 0xFF  # bad CRC
        elif kind < 0.65:
            frame = frame[: rng.randrange(1, len(frame))]  # truncated
        elif kind < 0.7:
            frame[7] = rng.randrange(256)  # unknown or wrong message id, CRC no longer matches
        yield bytes(frame)
