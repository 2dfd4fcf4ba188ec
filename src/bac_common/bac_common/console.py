"""Console output of the command-line tools (nodes log through their logger instead)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any


def say(text: str = "", *, err: bool = False, flush: bool = True) -> None:
    """Write one line of a CLI's output: its result on stdout, or a message for the user on stderr."""
    stream = sys.stderr if err else sys.stdout
    stream.write(f"{text}\n")
    if flush:
        stream.flush()


def in_range(kind: type, lower: float, upper: float) -> Callable[[str], Any]:
    """An argparse ``type`` that takes a number of ``kind`` within [lower, upper], the range the node that gets it
    declares: a value out of it is refused by the command line, not by the node after the graph started."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a{'n' if kind is int else ''} {kind.__name__}") from None
        if not lower <= value <= upper:
            raise argparse.ArgumentTypeError(f"{value} is outside [{kind(lower)}, {kind(upper)}]")
        return value

    return parse
