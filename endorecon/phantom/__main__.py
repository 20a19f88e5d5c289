"""``python -m endorecon.phantom out=<dir> [patients=14 frames=60 height=256 width=320 seed=0 mesh=<path>]``.

Keys and defaults live in ``conf/phantom.yaml``; arguments are ``key=value``
overrides of it (unknown keys are an error).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from endorecon.utils.errors import EndoreconError, InputError

CONF = Path(__file__).resolve().parents[2] / "conf" / "phantom.yaml"


def defaults() -> dict:
    """``out`` and the generator's keyword defaults: what applies when the package is installed without
    the conf/ folder next to it."""
    from endorecon.phantom.generate import generator_defaults

    return {"out": None, **generator_defaults()}


def parse_args(argv: list[str]) -> dict:
    """``key=value`` overrides of the phantom config -> kwargs of :func:`endorecon.phantom.generate`."""
    import yaml

    cfg = defaults()
    if CONF.is_file():
        cfg.update(yaml.safe_load(CONF.read_text()) or {})
    for arg in argv:
        if arg in ("-h", "--help"):
            print(__doc__.strip())
            print("keys: " + ", ".join(f"{k}={v}" for k, v in cfg.items()))
            sys.exit(0)
        if "=" not in arg:
            raise InputError(f"argument {arg!r} is not key=value", fix="e.g. python -m endorecon.phantom out=/tmp/ph frames=40")
        key, value = arg.split("=", 1)
        key = key.lstrip("+")
        if key not in cfg:
            raise InputError(f"unknown key {key!r}", CONF, "valid keys: " + ", ".join(cfg))
        cfg[key] = yaml.safe_load(value) if value != "" else None
    if not cfg.get("out"):
        raise InputError("no output folder given", fix="pass out=<dir>")
    return cfg


def main(argv: list[str] | None = None) -> int:
    import logging

    from endorecon.phantom import generate

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        cfg = parse_args(sys.argv[1:] if argv is None else argv)
        out = cfg.pop("out")
        t0 = time.perf_counter()
        path = generate(out, progress=True, **cfg)
        print(f"phantom written to {path} in {time.perf_counter() - t0:.1f} s")
    except EndoreconError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
