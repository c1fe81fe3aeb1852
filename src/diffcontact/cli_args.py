"""Helpers shared by the ``diffcontact`` subcommands and the scripts of experiments/ and
benchmarks/: argument types (argparse ``type=``), :func:`one_line` (the one-line form of
an error message), :func:`one_line_warnings` (warnings as one line each),
:func:`report_errors` (errors as one line on stderr and an exit status) and
:func:`interrupted` (a stop by Ctrl-C or SIGTERM as one line). No heavy imports."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import warnings
from collections.abc import Callable, Iterator
from typing import Any


def int_at_least(low: int) -> Callable[[str], int]:
    """An argparse type accepting integers ``>= low`` with a message naming the bound."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


positive_int = int_at_least(1)
non_negative_int = int_at_least(0)


def threads_arg(text: str) -> int | str:
    """An argparse type for ``--threads``: ``auto`` or an integer >= 1."""
    if text == "auto":
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 'auto' or >= 1, got {value}")
    return value


def float_above(low: float) -> Callable[[str], float]:
    """An argparse type accepting finite numbers ``> low`` with a message naming the bound."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (value > low and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"must be a finite number > {low:g}, got {text}")
        return value

    return parse


positive_float = float_above(0)
"""An argparse type accepting finite numbers > 0."""


def float_in(
    low: float, high: float = math.inf, *, infinite: bool = False
) -> Callable[[str], float]:
    """An argparse type accepting finite numbers in ``[low, high]`` with a message naming
    the range (``high = inf``: any finite number from ``low`` on; ``infinite``: ``inf``
    too, where it means "off")."""
    bracket = "]" if infinite or not math.isinf(high) else ")"
    kind = "a number" if infinite else "a finite number"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (low <= value <= high and (infinite or math.isfinite(value))):
            raise argparse.ArgumentTypeError(
                f"must be {kind} in [{low:g}, {high:g}{bracket}, got {value:g}"
            )
        return value

    return parse


def finite_float(text: str) -> float:
    """An argparse type accepting any finite number (NaN and infinities are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {value:g}")
    return value


def one_line(err: BaseException) -> str:
    """An exception message on one line (multi-line validation messages joined by '; ').

    ``"bad config:\\n  a: x\\n  b: y"`` becomes ``"bad config: a: x; b: y"``; an
    empty message gives the exception's type name.
    """
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    if len(lines) == 1:
        return lines[0]
    return f"{lines[0].rstrip(':')}: " + "; ".join(lines[1:])


@contextlib.contextmanager
def one_line_warnings(prog: str) -> Iterator[None]:
    """Print the warnings raised inside as ``PROG: warning: MESSAGE`` lines on stderr, each
    once (not Python's two lines with a file name and a source line), also when the block
    fails. The warning filters in force decide which are recorded, as they decide which
    Python shows (a library's DeprecationWarning stays hidden)."""
    with warnings.catch_warnings(record=True) as caught:
        try:
            yield
        finally:
            for message in dict.fromkeys(one_line(w.message) for w in caught):
                print(f"{prog}: warning: {message}", file=sys.stderr)


def report_errors(
    prog: str,
    run: Callable[[], int],
    *,
    bad_input: type[Exception] | tuple[type[Exception], ...],
    failures: tuple[type[Exception], ...] = (RuntimeError, OSError),
    failed: str = "",
) -> int:
    """The exit status of a subcommand's work ``run()``, its errors reported on one line.

    Returns what ``run`` returns; 2 after ``PROG: error: MESSAGE`` on stderr
    for a ``bad_input`` error; 1 after ``PROG: error: FAILED TYPE: MESSAGE``
    for one of ``failures``. Other exceptions propagate.
    """
    try:
        return run()
    except bad_input as err:
        print(f"{prog}: error: {one_line(err)}", file=sys.stderr)
        return 2
    except failures as err:
        print(f"{prog}: error: {failed}{type(err).__name__}: {one_line(err)}", file=sys.stderr)
        return 1


def interrupted(prog: str, stop: KeyboardInterrupt, hint: str) -> int:
    """Report a script stopped by Ctrl-C or SIGTERM on one line; its exit status.

    ``stop``: a ``KeyboardInterrupt``, or ``train()``'s ``TrainingInterrupted``, whose
    signal, exit status and checkpoint are named (its own message ends with the hint of
    ``diffcontact train``, ``continue with --resume``, which a script need not have).
    ``hint``: how this script continues, e.g. "run the same command again to continue".
    Prints ``PROG: SIGNAL received: stopped (checkpoint PATH); HINT`` on stderr and
    returns 128 + the signal's number (130 for Ctrl-C).
    """
    name = getattr(stop, "signal_name", None) or "SIGINT"
    checkpoint = getattr(stop, "checkpoint", None)
    where = f" (checkpoint {checkpoint})" if checkpoint else ""
    print(f"{prog}: {name} received: stopped{where}; {hint}", file=sys.stderr)
    return int(getattr(stop, "exit_status", 130))


def run_stoppable(main: Callable[[Any], int], argv: Any, prog: str, hint: str) -> int:
    """``main(argv)``, a script's command line, with a stop by Ctrl-C or SIGTERM reported
    on one line by :func:`interrupted` (``prog``, ``hint``: as there)."""
    try:
        return main(argv)
    except KeyboardInterrupt as stop:
        return interrupted(prog, stop, hint)
