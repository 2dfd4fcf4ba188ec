"""Console output of the command-line tools (nodes log through their logger instead)."""

from __future__ import annotations

import sys


def say(text: str = "", *, err: bool = False, flush: bool = True) -> None:
    """Write one line of a CLI's output: its result on stdout, or a message for the user on stderr."""
    stream = sys.stderr if err else sys.stdout
    stream.write(f"{text}\n")
    if flush:
        stream.flush()
