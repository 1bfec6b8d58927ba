"""The exception tree of both programs (the simulator raises the same config and camera errors).

Events (GPS loss, a lost leader) are mission inputs, never exceptions.
"""


class CompanionError(Exception):
    """Base of every error the service raises on purpose; the CLI maps subclasses to exit codes."""

    exit_code = 1


class ConfigError(CompanionError):
    """The configuration is invalid. Carries one human-readable line per problem.

    ``sources``, when given, names where each problem's value came from (a file, an environment
    variable), one per problem; otherwise every problem is ``source``'s.
    """

    exit_code = 2

    def __init__(self, source: str, problems: list[str], sources: list[str] | None = None) -> None:
        self.source = source
        self.problems = problems
        self.sources = sources if sources is not None else [source] * len(problems)
        super().__init__("\n".join(f"{s}: {p}" for s, p in zip(self.sources, problems, strict=True)))


class ModelError(CompanionError):
    """The detector model is missing, corrupt or does not match its checksum."""

    exit_code = 2


class CameraError(CompanionError):
    """The frame source cannot be opened (no device, missing library, unreadable recording)."""

    exit_code = 3


class LinkLostError(CompanionError):
    """The autopilot link could not be established or was lost for good."""

    exit_code = 3


class WrongVehicleError(CompanionError):
    """The link carries only autopilots this service must not fly (the leader's, or another system id).

    Exit code 4: a wiring or config mistake that a restart cannot fix (``RestartPreventExitStatus``).
    """

    exit_code = 4


class CommandRejectedError(CompanionError):
    """The autopilot refused a command (``result`` is the MAVLink MAV_RESULT or a MAVSDK result name)."""

    def __init__(self, command: str, result: str) -> None:
        self.command = command
        self.result = result
        super().__init__(f"{command} rejected: {result}")


def first_companion_error(group: BaseException) -> CompanionError | None:
    """The first of our own errors inside a (nested) exception group, such as a TaskGroup's; else None."""
    for exc in getattr(group, "exceptions", ()):
        if isinstance(exc, CompanionError):
            return exc
        found = first_companion_error(exc)
        if found is not None:
            return found
    return None
