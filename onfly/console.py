"""The toolkit's terminal writers for what is not a command's report: diagnostics and live status.

A command's report (tables, summaries, results) goes to stdout through
:func:`onfly.cli.echo`; what a person watches while it runs, and what went wrong on the way,
goes to stderr through these two, so that a report piped to a file holds the report alone.
Both flush: a status line is worth nothing when it arrives after the work.
"""

from __future__ import annotations

import sys
from typing import TextIO

__all__ = ["status", "live_line"]


def status(line: str = "", *, stream: TextIO | None = None) -> None:
    """Write ``line`` and a newline to ``stream`` (default: stderr), flushed."""
    s = stream if stream is not None else sys.stderr
    s.write(line + "\n")
    s.flush()


def live_line(line: str, *, width: int, final: bool = False, stream: TextIO | None = None) -> None:
    """A live status line on ``stream`` (default: stderr), flushed. On a terminal it is redrawn
    in place (a carriage return, cut and padded to ``width`` characters) and ends its line only
    when ``final``; elsewhere (a log file, a pipe) each call writes one line of its own."""
    s = stream if stream is not None else sys.stderr
    if s.isatty():
        s.write("\r" + line[:width].ljust(width) + ("\n" if final else ""))
        s.flush()
    else:
        status(line, stream=s)
