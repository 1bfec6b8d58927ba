"""moderngl plumbing shared by the renderer's passes: uniforms, matrices, write masks, program sets."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

#: A 4x4 identity as a uniform's bytes.
IDENTITY4 = np.eye(4, dtype=np.float32).tobytes()


def color_mask(fbo: moderngl.Framebuffer, masks: list[tuple[bool, bool, bool, bool]]) -> None:
    """Per-attachment colour write masks (the first ``len(attachments)`` of ``masks``)."""
    n = len(fbo.color_attachments)
    fbo.color_mask = masks[0] if n == 1 else masks[:n]  # type: ignore[assignment]


def mat_bytes(M: NDArray[np.float64]) -> bytes:
    """A numpy matrix as GLSL expects it (column-major float32)."""
    return np.ascontiguousarray(M.T, dtype=np.float32).tobytes()


def set_uniform(prog: moderngl.Program, name: str, value: Any) -> None:
    """Set a uniform if the linker kept it (unused uniforms are optimised away) and it changed.

    The program's ``extra`` caches each name's uniform (or None) and last value: setting one costs
    microseconds in moderngl, and a frame sets dozens, most of them unchanged.
    """
    cache: dict[str, list[Any]] | None = prog.extra
    if cache is None:
        cache = prog.extra = {}
    entry = cache.get(name)
    if entry is None:
        try:
            member: Any = prog[name]
        except KeyError:
            member = None
        entry = cache[name] = [member, None]
    if entry[0] is None or entry[1] == value:
        return
    entry[1] = value
    if isinstance(value, bytes):
        entry[0].write(value)
    else:
        entry[0].value = value


@dataclass(slots=True)
class ScenePrograms:
    """The scene pass's programs, compiled either for the post pass or DIRECT (sensor in the scene)."""

    ground: moderngl.Program
    generic: moderngl.Program
    foliage: moderngl.Program
    band: moderngl.Program
    diffuse: moderngl.Program
    rotor: moderngl.Program
    sky: moderngl.Program
    sky_vao: moderngl.VertexArray
    world_vaos: tuple[moderngl.VertexArray, ...] = ()
    leader_vaos: tuple[moderngl.VertexArray, ...] = ()
    dyn_vao: moderngl.VertexArray | None = None

    @property
    def all(self) -> tuple[moderngl.Program, ...]:
        return (*self.meshes, self.sky)

    @property
    def meshes(self) -> tuple[moderngl.Program, ...]:
        return (*self.world, self.rotor)

    @property
    def world(self) -> tuple[moderngl.Program, ...]:
        """The world's programs in the order of ``world.GROUPS``."""
        return (self.ground, self.generic, self.foliage, self.band, self.diffuse)
