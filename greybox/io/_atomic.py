"""Result folders and files: written atomically, never over anything greybox did not write.

The output contract of every command that writes a result folder (`greybox fit`,
`greybox simulate`, `greybox demo`):

- `check_output_dir` (called before any work): the folder must be absent, empty, or an
  earlier greybox result, recognised by the marker file `MARKER` that every result holds;
  anything else is refused with an `InputError` naming ``--out`` (``force=True`` overrides
  for a folder that is not a result, never for the current folder, one of its parents or a
  folder holding the input). Its parent must be writable.
- `atomic_output_dir` writes into a private folder beside the result and swaps it in with
  one atomic ``renameat2(RENAME_EXCHANGE)`` (Linux); where that call does not exist it
  falls back to two renames and `recover` undoes a crash between them (the old result is
  kept under ``.NAME.old-PID`` until the new one is in place, and the next run puts it
  back). A crash at any instant therefore leaves the old result or the new one.
- SIGINT and SIGTERM (`signal_handlers`, installed by the CLI for every command) raise
  `KeyboardInterrupt` / `Terminated` in the main thread and are remembered: a result is
  never swapped in after a signal, even one that some code caught and swallowed. One that
  lands where Python ignores exceptions (a gc callback such as JAX's, a ``__del__``, a
  weakref callback) reaches `sys.unraisablehook`, which delivers it again to the main thread
  just after, so the command stops there and then.
- Leftovers of killed runs (``.NAME.partial-PID-*``, ``.NAME.old-PID``) are removed by the
  next run once their process is gone. Writers of the same folder take an `fcntl.flock` on
  its parent folder while they clean up and swap, so concurrent runs never collide (the
  last one to finish wins).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import fcntl
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from greybox._model.errors import InputError

MARKER = ".greybox-result"
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM (handled like Ctrl-C)."""


_RECEIVED: list[int] = []  # the signals received while `signal_handlers` was active
_COMMITTED: list[Path] = []  # results swapped in under `signal_handlers` (what a late signal
# interrupts is then the report after the result, not the result)


_IN_HOOK: list[bool] = [False]  # True while `_on_unraisable` runs (see `_on_signal`)


def _on_signal(signum, frame):
    _RECEIVED.append(signum)
    if _IN_HOOK[0]:  # raised inside our own unraisable hook it would be lost for good; the
        return  # hook's delivery thread sends it again once the hook has returned
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def _on_unraisable(unraisable) -> None:
    """`sys.unraisablehook` under `signal_handlers`. Raised where Python ignores exceptions
    (a garbage-collector callback such as JAX's `_xla_gc_callback`, a ``__del__``, a weakref
    callback), our KeyboardInterrupt / `Terminated` would be printed as "Exception ignored"
    and lost, and the command would run on to its end: the signal is delivered again once
    the callback is over. Anything else goes to the previous hook."""
    if isinstance(unraisable.exc_value, (KeyboardInterrupt, Terminated)) and _RECEIVED:
        _IN_HOOK[0] = True  # starting a thread waits: a signal can land here (under load)
        try:
            threading.Thread(target=_deliver_again, args=(_RECEIVED[-1],), daemon=True).start()
        finally:
            _IN_HOOK[0] = False
        return
    _PREVIOUS_HOOK[-1](unraisable)


_PREVIOUS_HOOK: list = [sys.unraisablehook]


def _deliver_again(signum: int) -> None:
    """Send `signum` to the main thread itself (a sleep or a wait there is woken) once the
    hook that started this thread has returned, unless the command has ended meanwhile (its
    handlers are gone; `received_signal` has it)."""
    time.sleep(0.01)
    while _IN_HOOK[0]:
        time.sleep(0.005)
    if signal.getsignal(signum) is _on_signal:
        signal.pthread_kill(threading.main_thread().ident, signum)


def received_signal() -> int | None:
    """The first SIGINT/SIGTERM received under `signal_handlers`, or None."""
    return _RECEIVED[0] if _RECEIVED else None


def committed() -> list[Path]:
    """The result folders and files completed under the current `signal_handlers`."""
    return list(_COMMITTED)


def _check_not_interrupted() -> None:
    """Raise again a signal that arrived (and was swallowed by some code) before the commit."""
    if _RECEIVED:
        raise Terminated if _RECEIVED[0] == signal.SIGTERM else KeyboardInterrupt


@contextlib.contextmanager
def signal_handlers() -> Iterator[None]:
    """SIGINT -> KeyboardInterrupt, SIGTERM -> `Terminated`, both remembered (main thread only;
    the handlers are Python functions, so they run between bytecodes of the main thread and
    never inside compiled code or another thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _RECEIVED.clear()
    _COMMITTED.clear()
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    _PREVIOUS_HOOK.append(sys.unraisablehook)
    sys.unraisablehook = _on_unraisable
    try:
        yield
    finally:
        sys.unraisablehook = _PREVIOUS_HOOK.pop()
        for s, handler in previous.items():
            signal.signal(s, handler)


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


_LIBC = _libc()


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically; False where the system cannot."""
    fn = getattr(_LIBC, "renameat2", None) if _LIBC is not None else None
    if fn is None:
        return False
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def is_result(folder: Path) -> bool:
    return (Path(folder) / MARKER).is_file()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _leftovers(out: Path):
    """(kind, pid, path) of the partial and old folders a run writing `out` leaves behind."""
    pattern = re.compile(rf"^\.{re.escape(out.name)}\.(partial|old)-(\d+)(?:-.*)?$")
    if not out.parent.is_dir():
        return
    for p in out.parent.iterdir():
        m = pattern.match(p.name)
        if m:
            yield m.group(1), int(m.group(2)), p


def recover(out: str | os.PathLike) -> None:
    """Undo what killed runs left beside `out`: put back an old result that a crash left
    renamed away (when `out` is missing), remove partial and stale old folders."""
    out = Path(out)
    for kind, pid, p in sorted(_leftovers(out), key=lambda x: x[0] == "partial"):
        if _alive(pid):
            continue
        if kind == "old" and not out.exists() and is_result(p):
            os.replace(p, out)
        else:
            shutil.rmtree(p, ignore_errors=True)


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """An exclusive `flock` on `folder` (a directory fd: no lock file is left behind)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def can_make(path: Path) -> bool:
    """Whether this user may make `path` (a folder or file, with the folders missing above
    it) or write into it: it, or the nearest of its parents that exists, is a folder this
    user may write. Nothing is made."""
    base = _nearest_existing(Path(path))
    return base.is_dir() and os.access(base, os.W_OK | os.X_OK)


def check_output_dir(out, *, force: bool = False, inputs=(), field: str = "--out") -> Path:
    """Refuse an output folder that is not ours to replace; return it as an absolute path.

    `out` must be absent, empty or an earlier greybox result (holding `MARKER`); `force`
    allows replacing any other folder. The current folder, its parents and folders holding
    any of `inputs` are refused even with `force`. The nearest existing parent must be
    writable. Raises `InputError` naming `field`.
    """
    given = str(out)
    out = Path(os.path.abspath(out))
    cwd = Path.cwd().resolve()
    real = out.resolve()
    if real == cwd or real in cwd.parents or real == Path(real.anchor):
        raise InputError(
            "is the current folder or one of its parents; a result folder is replaced as a "
            "whole, so give a new folder name (e.g. results/run1)",
            file=given,
            field=field,
        )
    for inp in inputs:
        inp = Path(inp).resolve()
        if inp == real or real in inp.parents:
            raise InputError(
                f"holds the input {inp}; a result folder is replaced as a whole, so "
                "write it somewhere else (e.g. results/NAME)",
                file=given,
                field=field,
            )
    if out.exists() or out.is_symlink():
        if not out.is_dir() or out.is_symlink():
            raise InputError(
                "exists and is not a folder; give a new folder name",
                file=given,
                field=field,
            )
        if not is_result(out) and any(out.iterdir()) and not force:
            raise InputError(
                f"is a folder that greybox did not write (no {MARKER} marker) and it is not "
                "empty; nothing was changed. Give a new or empty folder, or pass --force to "
                "replace it and everything in it",
                file=given,
                field=field,
            )
    base = _nearest_existing(out.parent)
    if not base.is_dir():
        raise InputError(f"{base} is not a folder; give another --out", file=given, field=field)
    try:
        fd, probe = tempfile.mkstemp(prefix=".greybox-write-test-", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise InputError(
            f"cannot write into {base} ({err.strerror}); choose a writable folder",
            file=given,
            field=field,
        ) from None
    return out


def _write_marker(folder: Path, kind: str) -> None:
    from greybox import __version__

    (folder / MARKER).write_text(
        json.dumps({"greybox_result": kind, "greybox_version": __version__}) + "\n"
    )


@contextlib.contextmanager
def atomic_output_dir(
    out: str | os.PathLike, *, kind: str = "result", force: bool = False
) -> Iterator[Path]:
    """Yield a temporary directory beside `out`; on success it replaces `out` atomically.

    On any exception (including KeyboardInterrupt and the SIGTERM the CLI turns into one)
    the temporary directory is removed and `out` is left exactly as it was (absent, or the
    previous complete result). The new folder holds `MARKER`. An `out` that is neither
    absent, empty nor a greybox result is refused (`InputError`) unless `force`. An
    `OSError` while writing (read-only or full disk) becomes an `InputError` naming ``--out``.
    """
    out = Path(os.path.abspath(out))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with _locked(out.parent):
            recover(out)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-{os.getpid()}-", dir=out.parent))
    except OSError as err:
        raise _write_error(out, err) from None
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it owner-only; results are ordinary
        yield tmp
        _write_marker(tmp, kind)
        with _locked(out.parent):
            _check_not_interrupted()
            recover(out)
            if out.exists():
                if not (out.is_dir() and (is_result(out) or force or not any(out.iterdir()))):
                    raise InputError(
                        "was filled by something else while greybox ran; nothing was "
                        "replaced (pass --force to replace it)",
                        file=str(out),
                        field="--out",
                    )
                if _exchange(tmp, out):
                    _COMMITTED.append(out)
                    shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the old result
                    return
                old = out.with_name(f".{out.name}.old-{os.getpid()}")
                os.replace(out, old)  # a crash here: `recover` renames old back
                os.replace(tmp, out)
                _COMMITTED.append(out)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, out)
                _COMMITTED.append(out)
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        raise _write_error(out, err) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_error(out: Path, err: OSError) -> InputError:
    return InputError(
        f"cannot write the result ({err.strerror or err}); free space or choose a "
        "writable --out. An earlier result there is unchanged",
        file=str(out),
        field="--out",
    )


def check_output_file(path, *, ours, force: bool = False, field: str = "--out") -> Path:
    """The output-file contract (before any work): `path` is absent, or a file `ours(first
    line)` recognises as an earlier greybox result, or `force` is given; never a folder; its
    nearest existing parent is writable. Raises `InputError` naming `field`."""
    given = str(path)
    path = Path(os.path.abspath(path))
    if path.is_dir():
        raise InputError("is a folder; give the path of a file to write", file=given, field=field)
    if path.exists() or path.is_symlink():
        if not path.is_file() or path.is_symlink():
            raise InputError("exists and is not a plain file; give a new name", file=given,
                             field=field)  # fmt: skip
        try:
            with open(path, encoding="utf-8", errors="replace") as fh:
                first = fh.readline(10_000).rstrip("\r\n")
        except OSError as err:
            raise InputError(f"cannot be read ({err.strerror})", file=given, field=field) from None
        if not ours(first) and not force:
            raise InputError(
                "exists and was not written by greybox; nothing was changed. Give a new file "
                "name, or pass --force to replace it",
                file=given,
                field=field,
            )
    if not can_make(path.parent):
        base = _nearest_existing(path.parent)
        raise InputError(f"cannot write into {base}; choose a writable folder", file=given,
                         field=field)  # fmt: skip
    return path


def _umask() -> int:
    """The process's umask (read by setting it, so set back at once)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _file_mode(path: Path) -> int:
    """The permissions a written file gets: those of the file it replaces, else an ordinary
    new file's (0666 less the umask), as an editor or `open(path, "w")` would leave them."""
    try:
        return path.stat().st_mode & 0o777  # not its set-id or sticky bits
    except OSError:
        return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_output_file(path: str | os.PathLike, mode: str = "w") -> Iterator:
    """Open a temporary file beside `path`; it is renamed onto `path` only if the block
    succeeds. Whatever fails (the block, a signal, a full disk, a folder that appeared at
    `path`), the temporary file is removed; an `OSError` becomes an `InputError` on --out."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.partial-", dir=path.parent)
    except OSError as err:
        raise _write_error(path, err) from None
    try:
        os.fchmod(fd, _file_mode(path))  # mkstemp makes it owner-only (0600)
        with os.fdopen(fd, mode) as fh:
            yield fh
        _check_not_interrupted()
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "a folder appeared there", str(path))
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise _write_error(path, err) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _COMMITTED.append(path)
