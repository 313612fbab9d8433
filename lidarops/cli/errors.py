"""How every ``lidarops`` command reports a failure: one line on stderr and an exit code, no traceback.

A command's function is registered through :func:`guarded`::

    p.set_defaults(func=guarded("detect", detect))

and then ``lidarops detect /no/such.bin`` prints ``lidarops detect: error: /no/such.bin not found`` and
exits with 2. What counts as the user's error (a missing or unwritable file, a bad value, a config or
checkpoint lidarops cannot read, a missing optional package, a build without the kernels asked for) is
:func:`user_errors`; anything else is a bug and keeps its traceback. Ctrl-C prints
``lidarops <command>: interrupted`` and exits with 130, the shell's code for SIGINT.

Exit codes: 0 success, 1 a command's own "ran, but the check failed" (``lidarops stream``'s identity
check, ``lidarops tour``'s references), 2 an error, 130 interrupted. argparse's own usage errors also
exit with 2.
"""
from __future__ import annotations

import argparse
import sys
from typing import Callable

__all__ = ["CliError", "EXIT_ERROR", "EXIT_INTERRUPTED", "user_errors", "guarded", "one_line"]

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT


class CliError(Exception):
    """An error of the command's input, reported as one line (exit code 2)."""


def user_errors() -> tuple[type[BaseException], ...]:
    """The exception classes reported as one line: the user's to fix, not lidarops' bugs."""
    # OSError rather than only FileNotFoundError / FileExistsError / NotADirectoryError: an output that
    # cannot be written (PermissionError, IsADirectoryError, a full disk) is the user's to fix as well.
    # ValueError covers lidarops.config.ConfigError and lidarops.checkpoint.CheckpointError.
    from lidarops.extension import LidaropsBuildError  # imports torch: only once a command has failed

    return CliError, OSError, ValueError, ImportError, LidaropsBuildError


def one_line(message: object) -> str:
    """``message`` with its line breaks and runs of spaces collapsed to single spaces."""
    return " ".join(str(message).split())


def guarded(name: str, fn: Callable[[argparse.Namespace], "int | None"]) -> Callable[[argparse.Namespace], int]:
    """``fn`` as a command: its return value (None: 0) is the exit code; a user error (:func:`user_errors`)
    becomes ``lidarops <name>: error: <message>`` on one line of stderr and exit code 2; KeyboardInterrupt
    becomes ``lidarops <name>: interrupted`` and exit code 130.

    Args:
        name: the command as typed after ``lidarops`` (``"detect"``, ``"data synth"``).
        fn: the command's function, taking the parsed arguments.
    """

    def run(args: argparse.Namespace) -> int:
        try:
            return int(fn(args) or 0)
        except KeyboardInterrupt:
            print(f"lidarops {name}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except Exception as e:  # noqa: BLE001  (sorted below; a bug re-raises with its traceback)
            if not isinstance(e, user_errors()):
                raise
            print(f"lidarops {name}: error: {one_line(e) or type(e).__name__}", file=sys.stderr)
            return EXIT_ERROR

    run.__name__ = run.__qualname__ = f"lidarops {name}"
    run.__doc__ = fn.__doc__
    return run

