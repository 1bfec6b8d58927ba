"""``sitl`` with the lab's components passed in: what ``companion sim``'s real path starts.

``python -m companion.lab.evaluation.sitl_host serve ...`` takes ``sitl``'s own arguments and runs
``sitl serve`` with :func:`companion.lab.evaluation.sitl_components.run` beside the simulation, handed
over as a callable: the simulator never imports a lab module by name.
"""

from __future__ import annotations

from collections.abc import Sequence

from companion.lab.evaluation.sitl_components import run
from sitl.cli import main as sitl_main


def main(argv: Sequence[str] | None = None) -> int:
    """``sitl``'s command line, its ``serve`` hosting the lab's components."""
    return sitl_main(argv, components=(run,))


if __name__ == "__main__":
    raise SystemExit(main())
