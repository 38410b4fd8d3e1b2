"""The output contract: nothing lost, nothing half-written, nothing hangs.

A result folder is written only over an absent, empty or earlier greybox folder (marker
file), swapped in atomically, recovered after a crash at any instant, cleaned of what killed
runs left, safe under concurrent writers; SIGTERM is handled like Ctrl-C; a bug is exit 3,
never disguised as bad input. No test here compiles a model (all fast).
"""

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import greybox.io._atomic as atomic
from greybox._model.errors import InputError
from greybox.cli import main
from greybox.io._atomic import MARKER, atomic_output_dir, check_output_dir, recover

ROOT = Path(__file__).resolve().parents[1]
EMBEDDED = ROOT / "experiments" / "chevron_laser"


def _result(folder: Path, text: str) -> Path:
    with atomic_output_dir(folder) as tmp:
        (tmp / "params.json").write_text(text)
    return folder


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# ----------------------------------------------------------------------------------------
# --out must be absent, empty or an earlier result: refused before any work


@pytest.mark.parametrize("command", ["fit", "simulate", "demo"])
def test_foreign_folder_is_refused_before_any_work(tmp_path, capsys, command):
    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.tex").write_text("precious")
    argv = {
        "fit": ["fit", str(EMBEDDED), "--quiet"],
        "simulate": ["simulate", "--params", "nowhere.json", "--waveform", "pulse:x"],
        "demo": ["demo", "--quiet"],
    }[command]
    t0 = time.perf_counter()
    assert main([*argv, "--out", str(d)]) == 2
    assert time.perf_counter() - t0 < 5  # before loading or compiling anything
    err = capsys.readouterr().err
    assert "--out" in err and "--force" in err and MARKER in err
    assert sorted(p.name for p in d.iterdir()) == ["thesis.tex"]
    assert (d / "thesis.tex").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


@pytest.mark.parametrize("where", [".", "..", "experiment", "parent-of-experiment"])
def test_out_that_holds_cwd_or_the_input_is_refused_even_with_force(
    tmp_path, monkeypatch, capsys, where
):
    exp = tmp_path / "proj" / "exp"
    exp.mkdir(parents=True)
    (exp / "experiment.toml").write_text("")
    monkeypatch.chdir(exp)
    out = {".": ".", "..": "..", "experiment": str(exp), "parent-of-experiment": str(exp.parent)}
    assert main(["fit", str(exp), "--out", out[where], "--force", "--quiet"]) == 2
    assert "--out" in capsys.readouterr().err
    assert (exp / "experiment.toml").exists()


def test_unwritable_out_is_refused_before_loading(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["fit", str(EMBEDDED), "--out", str(blocker / "res"), "--quiet"]) == 2
    assert "--out" in capsys.readouterr().err
    with pytest.raises(InputError, match="not a folder"):
        check_output_dir(blocker)


def test_write_error_is_located_and_keeps_the_old_result(tmp_path, monkeypatch):
    out = _result(tmp_path / "res", "old")

    with pytest.raises(InputError, match="--out.*No space left"):
        with atomic_output_dir(out):
            raise OSError(28, "No space left on device")
    assert (out / "params.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_marker_force_and_replacement(tmp_path):
    out = _result(tmp_path / "res", "one")
    assert (out / MARKER).is_file()
    check_output_dir(out)  # an earlier result may be replaced
    _result(out, "two")
    assert (out / "params.json").read_text() == "two"
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "a").write_text("a")
    with pytest.raises(InputError, match="did not write"):
        check_output_dir(foreign)
    check_output_dir(foreign, force=True)
    with atomic_output_dir(foreign, force=True) as tmp:
        (tmp / "params.json").write_text("forced")
    assert sorted(p.name for p in foreign.iterdir()) == [MARKER, "params.json"]
    (tmp_path / "empty").mkdir()
    check_output_dir(tmp_path / "empty")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "foreign", "res"]


def test_written_files_and_folders_get_ordinary_permissions(tmp_path):
    """A result is what `open(path, "w")` and `mkdir` would leave under the umask (the private
    temporaries are owner-only, 0600 and 0700); a replaced file keeps its own permissions."""
    old = os.umask(0o027)
    try:
        with atomic.atomic_output_file(tmp_path / "tracks.csv") as fh:
            fh.write("t,x\n")
        with atomic_output_dir(tmp_path / "res") as tmp:
            (tmp / "params.json").write_text("{}")
    finally:
        os.umask(old)
    assert (tmp_path / "tracks.csv").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "res").stat().st_mode & 0o777 == 0o750
    (tmp_path / "tracks.csv").chmod(0o604)
    with atomic.atomic_output_file(tmp_path / "tracks.csv") as fh:
        fh.write("t,x\n0,1\n")
    assert (tmp_path / "tracks.csv").stat().st_mode & 0o777 == 0o604
    assert (tmp_path / "tracks.csv").read_text() == "t,x\n0,1\n"


def test_folder_filled_while_running_is_not_replaced(tmp_path):
    out = tmp_path / "res"
    with pytest.raises(InputError, match="filled by something else"):
        with atomic_output_dir(out) as tmp:
            (tmp / "params.json").write_text("new")
            out.mkdir()
            (out / "notes.txt").write_text("mine")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


# ----------------------------------------------------------------------------------------
# a crash at any instant leaves the old or the new result


def test_two_rename_fallback_and_crash_between_the_renames_recovers(tmp_path, monkeypatch):
    out = _result(tmp_path / "res", "old")
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)  # no renameat2
    _result(out, "new")  # the fallback path works
    assert (out / "params.json").read_text() == "new"
    # a process killed between its two renames left the old result renamed away
    pid = _dead_pid()
    os.replace(out, tmp_path / f".res.old-{pid}")
    assert not out.exists()
    recover(out)
    assert (out / "params.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_killed_runs_leftovers_are_cleaned_by_the_next_run(tmp_path):
    out = _result(tmp_path / "res", "old")
    dead = _dead_pid()
    (tmp_path / f".res.partial-{dead}-abc").mkdir()
    (tmp_path / f".res.old-{dead}").mkdir()  # not a result: removed, never restored
    alive = tmp_path / f".res.partial-{os.getppid()}-xyz"  # a live writer's: kept
    alive.mkdir()
    _result(out, "new")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [alive.name, "res"]
    assert (out / "params.json").read_text() == "new"


def test_the_swap_is_one_atomic_exchange(tmp_path, monkeypatch):
    out = _result(tmp_path / "res", "old")
    calls = []
    real = atomic._exchange

    def spy(a, b):
        calls.append((a, b))
        assert (b / "params.json").read_text() == "old"  # old result in place until the swap
        return real(a, b)

    monkeypatch.setattr(atomic, "_exchange", spy)
    monkeypatch.setattr(atomic.os, "replace", None)  # no rename pair may run
    with atomic_output_dir(out) as tmp:
        (tmp / "params.json").write_text("new")
    assert len(calls) == 1 and (out / "params.json").read_text() == "new"


def _writer(args):
    out, rounds, tag = args
    for k in range(rounds):
        with atomic_output_dir(out) as tmp:
            (tmp / "params.json").write_text(f"{tag}-{k}")
    return True


def test_concurrent_writers_never_collide(tmp_path):
    out = tmp_path / "res"
    with mp.get_context("fork").Pool(2) as pool:
        assert all(pool.map(_writer, [(out, 60, "a"), (out, 60, "b")]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    assert (out / "params.json").read_text() in ("a-59", "b-59")


# ----------------------------------------------------------------------------------------
# signals and exit statuses

_SLOW_COMMAND = textwrap.dedent(
    """
    import signal, sys, time
    import greybox.cli._fit as f
    from greybox.io._atomic import atomic_output_dir

    # as in a terminal: a test runner started in the background (CI, an xdist worker) hands
    # its children SIGINT ignored, which Python then keeps; Ctrl-C reaches a foreground one
    signal.signal(signal.SIGINT, signal.default_int_handler)

    def run(args):
        with atomic_output_dir(args.out) as tmp:
            (tmp / "params.json").write_text("new")
            print("ready", flush=True)
            time.sleep(60)
        return 0

    f.run = run
    from greybox.cli import main
    sys.exit(main(["fit", "x", "--out", sys.argv[1]]))
    """
)


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_and_sigint_leave_the_old_result_and_say_so(tmp_path, sig, status):
    out = _result(tmp_path / "res", "old")
    p = subprocess.Popen(
        [sys.executable, "-c", _SLOW_COMMAND, str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert p.stdout.readline().strip() == "ready"
    p.send_signal(sig)
    _, err = p.communicate(timeout=30)
    assert p.returncode == status
    assert "no result was written" in err and "Traceback" not in err
    assert (out / "params.json").read_text() == "old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["res"]


def test_sigkill_leftover_is_removed_by_the_next_run(tmp_path):
    out = _result(tmp_path / "res", "old")
    p = subprocess.Popen(
        [sys.executable, "-c", _SLOW_COMMAND, str(out)], stdout=subprocess.PIPE, text=True
    )
    assert p.stdout.readline().strip() == "ready"
    p.kill()
    p.wait()
    assert any(x.name.startswith(".res.partial-") for x in tmp_path.iterdir())
    assert (out / "params.json").read_text() == "old"
    _result(out, "next")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["res"]


def test_a_bug_is_exit_3_with_traceback_not_bad_input(monkeypatch, capsys):
    import greybox.cli._fit as f

    def broken(args):
        raise ValueError("internal inconsistency")

    monkeypatch.setattr(f, "run", broken)
    assert main(["fit", "x"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" in err and "internal inconsistency" in err and "report" in err

    def bad_input(args):
        raise InputError("bad", file="f.toml", line=3, field="k")

    monkeypatch.setattr(f, "run", bad_input)
    assert main(["fit", "x"]) == 2
    assert capsys.readouterr().err.strip() == "greybox fit: error: f.toml:3: k: bad"
