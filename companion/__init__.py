"""Wingman companion service: see the README. Importing this package has no side effects."""

__version__ = "0.2.0"
