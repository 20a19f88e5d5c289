"""Entry-point helpers: turn user-facing errors into one clean message and exit status 2."""

from __future__ import annotations

import sys

from endorecon.utils.errors import EndoreconError


def report_errors(fn, *args, **kwargs):
    """Call ``fn``; an :class:`EndoreconError` is printed as one message (no traceback) and exits with 2."""
    try:
        return fn(*args, **kwargs)
    except EndoreconError as e:
        try:
            from rich.console import Console
            from rich.text import Text

            # Text, not markup: messages hold paths and overrides with brackets.
            Console(stderr=True).print(Text("error: ", style="bold red") + Text(str(e)), highlight=False)
        except Exception:  # rich missing or broken terminal: plain text still says it
            print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
