"""The `greybox` command: a thin shell over the library (argument parsing, files, progress).

Each subcommand lives in its own module `greybox.cli._<name>` exposing
``add_parser(subparsers)`` (which sets ``func`` on its parser). Bad input raises
`greybox._model.errors.InputError`; `main` turns it into one line on stderr and exit status 2.
An exception (or ``sys.exit``) raised by a user's own device code is the user's error: one
line naming their file and line, exit 2. Any other exception is a bug in greybox: `main`
prints its traceback, asks for a report and returns 3. SIGINT and SIGTERM are handled the
same way by every command (`greybox.io._atomic.signal_handlers`: no partial result, exit 130
or 143), and a program run from the command line then ends without the interpreter's
teardown (JAX's atexit clean-up swallowed a late signal into exit 0).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import traceback

from greybox.io._atomic import Terminated, committed, received_signal, signal_handlers

SUBCOMMANDS = ("fit", "compare", "simulate", "describe", "demo", "track", "design", "fit-many")

DESCRIPTION = """\
greybox: fit physical parameters of laser-actuated thermal MEMS to camera data.

Units: time in s (`t_s`), displacement in um (`y_um`) or pixels (`y_px`, converted with
the experiment's um-per-pixel), laser power in mW on the command line and in files
(`laser_mW`), W inside the library. Every fit reports whether its numbers are free-run
simulation or one-step prediction.
"""


EXIT_STATUS = """\
Exit status (every command): 0 done; 1 written but not trustworthy (the fit did not
converge, see report.md); 2 bad input or output location, or an error in your own device
code (one line naming the file, line and field, nothing written); 3 a bug in greybox (a
traceback follows; please report it); 130 interrupted (Ctrl-C); 143 terminated (SIGTERM).
An interrupted or terminated run leaves no partial result and an earlier result unchanged.

Compiled programs are kept in your cache folder (greybox/jax), so running a command again
skips compiling them; GREYBOX_COMPILE_CACHE=off keeps none, GREYBOX_COMPILE_CACHE=FOLDER
keeps them there.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="greybox",
        description=DESCRIPTION,
        epilog=EXIT_STATUS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"greybox.cli._{name.replace('-', '_')}")
        except ModuleNotFoundError as err:
            if err.name != f"greybox.cli._{name.replace('-', '_')}":
                raise
            continue
        module.add_parser(sub)
    return parser


def main(argv=None) -> int:
    """Run one command. Bad input (`InputError`) -> one line and exit 2; any other exception
    is a bug: its traceback, a request to report it, exit 3 (never disguised as bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    code = _run(args, program=argv is None)
    if argv is None:  # the program itself, not a caller in Python: end it here
        _exit_now(code)
    return code


def _exit_now(code: int) -> None:
    """Exit with `code` without the interpreter's teardown. Everything greybox writes is
    closed and renamed by now; what is left is JAX's atexit clean-up and the destruction of
    its runtime, which a late SIGINT/SIGTERM turned into a swallowed signal (exit 0, the
    KeyboardInterrupt landed in jax's `clean_up`). (`_run` has blocked both signals.)"""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said
            pass
    os._exit(code)


def _run(args, *, program: bool = False) -> int:
    from greybox._model.errors import InputError
    from greybox._usercode import blame_user, stop_behind

    with signal_handlers():
        try:
            code = int(args.func(args) or 0)
        except BaseException as err:
            code = _failure(args, err, InputError, blame_user, stop_behind)
        if program:  # no signal may land between here and the exit
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    late = received_signal()
    if late is not None and code not in (130, 143):  # a signal some code swallowed
        what = "terminated" if late == signal.SIGTERM else "interrupted"
        print(f"greybox {args.command}: {what} (after the command had finished)", file=sys.stderr)
        return 143 if late == signal.SIGTERM else 130
    return code


def _failure(args, err, InputError, blame_user, stop_behind) -> int:
    """The exit status of a command that raised `err` (after saying why on stderr)."""
    stop = stop_behind(err)  # a Ctrl-C or SIGTERM, even where Python wrapped it
    if isinstance(stop, (KeyboardInterrupt, Terminated)):
        err = stop
    if isinstance(err, (Exception, SystemExit)) and not isinstance(err, InputError):
        blamed = blame_user(err)  # the user's device code, not greybox, failed
        if blamed is not None:
            err = blamed
        elif isinstance(err, SystemExit):
            raise err
    try:
        raise err
    except InputError as err:
        message = " ".join(str(err).split())  # one line, whatever the message held
        print(f"greybox {args.command}: error: {message}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, Terminated) as stop:
        what = "interrupted" if isinstance(stop, KeyboardInterrupt) else "terminated (SIGTERM)"
        done = committed()
        if done:  # the signal came after the swap: say so, the result is whole
            written = ", ".join(str(p) for p in done)
            print(f"greybox {args.command}: {what} after {written} was written", file=sys.stderr)
        else:
            print(f"greybox {args.command}: {what}; no result was written", file=sys.stderr)
        return 130 if isinstance(stop, KeyboardInterrupt) else 143
    except MemoryError:
        print(
            f"greybox {args.command}: error: out of memory; the problem is too large for "
            "this machine (decimate or split the runs, use fewer starts)",
            file=sys.stderr,
        )
        return 2
    except Exception:
        traceback.print_exc()
        print(
            f"greybox {args.command}: internal error (a bug in greybox "
            f"{_version()}, not a problem with your input); please report it with the "
            "traceback above and the command line. Nothing was written.",
            file=sys.stderr,
        )
        return 3


def _version() -> str:
    try:
        from greybox import __version__

        return __version__
    except Exception:
        return "(unknown version)"


if __name__ == "__main__":
    sys.exit(main())
