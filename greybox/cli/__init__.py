"""The `greybox` command: a thin shell over the library (argument parsing, files, progress).

Each subcommand lives in its own module `greybox.cli._<name>` exposing
``add_parser(subparsers)`` (which sets ``func`` on its parser). Bad input raises
`greybox._errors.InputError` (or `ValueError`); `main` turns it into one line on stderr and
exit status 2, so no subcommand prints tracebacks at users.
"""

from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS = ("fit", "simulate", "demo", "track")

DESCRIPTION = """\
greybox: fit physical parameters of laser-actuated thermal MEMS to camera data.

Units: time in s (`t_s`), displacement in um (`y_um`) or pixels (`y_px`, converted with
the experiment's um-per-pixel), laser power in mW on the command line and in files
(`laser_mW`), W inside the library. Every fit reports whether its numbers are free-run
simulation or one-step prediction.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="greybox",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"greybox.cli._{name}")
        except ModuleNotFoundError as err:
            if err.name != f"greybox.cli._{name}":
                raise
            continue
        module.add_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    from greybox._errors import InputError

    try:
        return int(args.func(args) or 0)
    except (InputError, ValueError, FileNotFoundError) as err:
        message = " ".join(str(err).split())  # one line, whatever the message held
        print(f"greybox {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"greybox {args.command}: interrupted; no result was written", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
