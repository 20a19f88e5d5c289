"""Entry-point helpers: turn user-facing errors into one clean message and exit status 2."""

from __future__ import annotations

import re
import sys

from endorecon.utils.errors import EndoreconError


def quote_path_overrides(argv: list[str], keys: tuple[str, ...]) -> list[str]:
    """Quote the values of path overrides (``key=path`` for ``key`` in ``keys``) so that Hydra's grammar
    accepts any path, e.g. one under ``outputs/train/fold=0/iteration=1/`` (an unquoted ``=`` in a value
    is a Hydra syntax error).  With ``-m`` / ``--multirun`` a comma separates the paths of a sweep
    (``input=a.mp4,b.mp4``: two jobs), so each is quoted on its own."""
    multirun = any(a in ("-m", "--multirun") for a in argv)

    def quote(v: str) -> str:
        # inside a quoted Hydra string a backslash escapes only before a quote or at the end of the string
        v = re.sub(r"(\\*)'", lambda m: m.group(1) * 2 + "\\'", v)
        v = re.sub(r"(\\+)$", lambda m: m.group(1) * 2, v)
        return "'" + v + "'"

    out = []
    for arg in argv:
        m = re.fullmatch(rf"(\+{{0,2}}(?:{'|'.join(map(re.escape, keys))}))=(.*)", arg, flags=re.S)
        sweep_fn = multirun and m and re.fullmatch(r"(choice|glob|range|sort|shuffle)\(.*\)", m.group(2), flags=re.S)
        if m and m.group(2) and m.group(2)[0] not in "'\"" and m.group(2) != "null" and not sweep_fn:
            items = m.group(2).split(",") if multirun else [m.group(2)]
            arg = f"{m.group(1)}=" + ",".join(v if v == "null" else quote(v) for v in items)
        out.append(arg)
    return out


def print_error(e: BaseException) -> None:
    """``error: <message>`` on stderr, as one message (the command lines' way of reporting an input error)."""
    try:
        from rich.console import Console
        from rich.text import Text

        # Text, not markup: messages hold paths and overrides with brackets.
        # not wrapped at the terminal's width: a path or an override cut in two cannot be copied
        Console(stderr=True).print(Text("error: ", style="bold red") + Text(str(e)), highlight=False,
                                   soft_wrap=True)
    except Exception:  # rich missing or broken terminal: plain text still says it
        print(f"error: {e}", file=sys.stderr)


def report_errors(fn, *args, **kwargs):
    """Call ``fn``; an :class:`EndoreconError` is printed as one message (no traceback) and exits with 2."""
    try:
        return fn(*args, **kwargs)
    except EndoreconError as e:
        print_error(e)
        sys.exit(2)
