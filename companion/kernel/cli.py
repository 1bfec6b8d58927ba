"""Command-line helpers shared by the ``companion`` and ``sitl`` programs."""

from __future__ import annotations

import argparse


def describe_commands(parser: argparse.ArgumentParser) -> None:
    """Give every (sub)command without a description its one-line help as one.

    So ``companion CMD --help`` says what the command does, not only its options.
    """
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        helps = {a.dest: a.help for a in action._choices_actions}
        for name, sub in action.choices.items():
            if not sub.description and helps.get(name):
                text = str(helps[name])
                sub.description = text[0].upper() + text[1:] + ("" if text.endswith(".") else ".")
            describe_commands(sub)
