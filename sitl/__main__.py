"""``python -m sitl``."""

from sitl.cli import main

raise SystemExit(main())
