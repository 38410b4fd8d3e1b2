"""User code at the library's edge: which code is the user's, consent to run it, its failures.

A device file named by an experiment, or by a params.json, is Python that greybox imports.
This module holds the three rules about such code, shared by every loader and command:

- **Trust** (`trusted_devices`): while a params.json is being loaded, a device reference that
  is a file resolves only inside the params.json's own folder, or inside a path the user
  named with ``--trust-device``; a module reference must belong to an installed package.
  A params.json is data, and opening data must not run code nobody asked for.
- **Blame** (`user_frame`, `UserCodeError`): an exception (or ``sys.exit``) raised by a
  device's own code is the user's error: exit 2 naming their file and line, never a
  greybox bug.
- **Bounds** (`time_limit`, `running_users_code`): importing and building a device, and a
  trial simulation of its model at load, are bounded in time, so a device that hangs cannot
  hang the command.
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib.metadata
import math
import os
import signal
import sys
import threading
import traceback
from pathlib import Path

from greybox._model.errors import InputError

#: seconds a device may take to import, check and build (GREYBOX_DEVICE_TIMEOUT_S overrides)
DEVICE_TIMEOUT_S = 120.0

_USER_ROOTS: set[Path] = set()  # folders (or files) whose code is a user's device code


def register_user_code(location: str | os.PathLike) -> None:
    """Record that the code at `location` (a file or its folder) is a user's device code."""
    _USER_ROOTS.add(Path(location).resolve())


# never the user's, even when a device folder holds them (a device file at a checkout's root)
_NOT_USERS = (Path(__file__).resolve().parent, Path(sys.prefix).resolve(),
              Path(sys.base_prefix).resolve())  # fmt: skip


def _in_user_code(filename: str) -> bool:
    try:
        p = Path(filename).resolve()
    except (OSError, ValueError):
        return False

    def inside(a: Path, b: Path) -> bool:
        return a == b or b in a.parents

    for root in _USER_ROOTS:
        # greybox itself and the environment stay greybox's even under a user's folder,
        # unless the user's device is itself installed there (a device package)
        if inside(p, root) and not any(inside(p, q) and not inside(root, q) for q in _NOT_USERS):
            return True
    return False


def user_frame(err: BaseException) -> tuple[str, int] | None:
    """(file, line) of the innermost frame of a user's device code in `err`'s traceback (or
    its cause's), or None when no user code is involved."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, SyntaxError) and err.filename and _in_user_code(err.filename):
            return err.filename, int(err.lineno or 0)
        found = None
        for frame in traceback.extract_tb(err.__traceback__):
            if _in_user_code(frame.filename):
                found = (frame.filename, int(frame.lineno or 0))
        if found:
            return found
        err = err.__cause__ or err.__context__
    return None


class UserCodeError(InputError):
    """A user's device code failed (raised, exited or hung): their file and line, exit 2."""


def blame_user(err: BaseException, context: str = "") -> UserCodeError | None:
    """A `UserCodeError` located at the user's line that raised `err` (`context`: what greybox
    was doing, e.g. "importing device file msd.py"), or None if `err` did not come from a
    user's code."""
    where = user_frame(err)
    if where is None:
        return None
    if isinstance(err, SystemExit):
        text = f"called sys.exit({err.code!r}); a device must not exit the program"
    elif isinstance(err, SyntaxError):
        text = f"syntax error: {err.msg}"
    else:
        text = f"raised {type(err).__name__}: {' '.join(str(err).split())[:300]}"
    during = f" while {context}" if context else ""
    return UserCodeError(
        f"the device code {text}{during} (an error in the device's code, not in greybox or "
        "your data; fix it there)",
        file=where[0],
        line=where[1],
    )


def stop_behind(err: BaseException | None) -> BaseException | None:
    """The KeyboardInterrupt, SIGTERM (the CLI's `Terminated`) or `time_limit` alarm that
    `err` is or wraps, else None: its causes, and its contexts unless suppressed (``raise
    ... from None``). Raised by a signal handler while Python creates a class (inside a
    descriptor's `__set_name__`, which every `eqx.Module` field has), such a stop surfaces
    as "RuntimeError: Error calling __set_name__" with the stop as its cause: it is the
    signal or the time limit, not an error of the code that was running."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, (KeyboardInterrupt, _TimedOut)) or type(err).__name__ == "Terminated":
            return err
        seen.add(id(err))
        err = err.__cause__ or (None if err.__suppress_context__ else err.__context__)
    return None


def _timeout_s() -> float:
    try:
        v = float(os.environ.get("GREYBOX_DEVICE_TIMEOUT_S", DEVICE_TIMEOUT_S))
    except ValueError:
        return DEVICE_TIMEOUT_S
    return v if math.isfinite(v) and v > 0 else DEVICE_TIMEOUT_S


class _TimedOut(BaseException):
    """Raised by the alarm inside the bounded block (a BaseException: user code's
    ``except Exception`` cannot swallow it)."""


@contextlib.contextmanager
def time_limit(what: str, location: str | None = None, seconds: float | None = None):
    """Bound the block to `seconds` of wall time (main thread only: a SIGALRM timer); on
    expiry raise a `UserCodeError` naming `what` and `location`. Nested limits keep the
    outer one."""
    seconds = _timeout_s() if seconds is None else seconds
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getitimer(signal.ITIMER_REAL)[0] > 0
    ):
        yield
        return

    def alarm(signum, frame):
        raise _TimedOut

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    except BaseException as err:
        stop = stop_behind(err)
        if not isinstance(stop, _TimedOut):
            raise
        where = user_frame(stop)  # the user's line that was running when time ran out
        raise UserCodeError(
            f"{what} did not finish in {seconds:g} s (a loop that never ends, or waiting on "
            "something); fix the device code, or raise GREYBOX_DEVICE_TIMEOUT_S if it is "
            "really that slow",
            file=location if where is None else where[0],
            line=None if where is None else where[1],
        ) from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def running_users_code(what: str, location: str | None = None):
    """Run the block (which calls a device's own code) bounded by `time_limit`; an exception
    or ``sys.exit`` raised by the user's code becomes a `UserCodeError` at their line."""
    try:
        with time_limit(what, location):
            yield
    except UserCodeError:
        raise
    except (Exception, SystemExit) as err:
        stop = stop_behind(err)
        if stop is not None:  # a signal that landed while the user's class was created
            raise stop from None
        blamed = blame_user(err, what)
        if blamed is None:
            raise
        raise blamed from None


# -- trust -------------------------------------------------------------------------------------

_TRUST: contextvars.ContextVar = contextvars.ContextVar("greybox_device_trust", default=None)


class UntrustedDevice(InputError):
    """A params.json names device code outside the places it may come from."""


@contextlib.contextmanager
def trusted_devices(params_path, trust=()):
    """While loading `params_path`, allow device files only inside its folder or inside the
    files/folders in `trust` (``--trust-device``), and modules only of installed packages."""
    params_path = Path(params_path)
    roots = [params_path.resolve().parent] + [Path(t).resolve() for t in (trust or ())]
    for given, root in zip(trust or (), roots[1:]):
        if not root.exists():
            raise InputError(
                "does not exist; give the device file (or its folder) you trust",
                file=str(given),
                field="--trust-device",
            )
    token = _TRUST.set((str(params_path), tuple(roots)))
    try:
        yield
    finally:
        _TRUST.reset(token)


@contextlib.contextmanager
def params_trust(params_path, trust=()):
    """`trusted_devices(params_path, trust)` unless a command already set the trust (with its
    --trust-device paths): loading a params.json is never consent by itself."""
    if _TRUST.get() is not None:
        yield
        return
    with trusted_devices(params_path, trust):
        yield


def _refuse(what: str) -> None:
    params, _ = _TRUST.get()
    raise UntrustedDevice(
        f"{what}; a params.json is data and greybox runs no code it names from elsewhere "
        "without your consent. If you trust that code, pass --trust-device PATH (the file or "
        "its folder), or copy the device file beside params.json",
        file=params,
        field="device",
    )


def check_device_file(path: Path) -> None:
    """Refuse (`UntrustedDevice`) a device file outside the trusted places, when a params.json
    is being loaded; no-op otherwise (an experiment folder or a command line is consent)."""
    trust = _TRUST.get()
    if trust is None:
        return
    real = Path(path).resolve()
    if any(real == r or r in real.parents for r in trust[1]):
        return
    _refuse(f"names the device file {real}, outside the params.json's folder")


def check_device_module(name: str) -> None:
    """Refuse a module reference that no installed distribution provides (while loading a
    params.json): otherwise the current folder or PYTHONPATH could supply the code."""
    if _TRUST.get() is None:
        return
    top = name.split(".")[0]
    try:
        installed = top in importlib.metadata.packages_distributions()
    except Exception:  # a broken metadata entry must not open the door
        installed = False
    if not installed:
        _refuse(f"names the module {name!r}, which no installed package provides")
