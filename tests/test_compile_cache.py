"""Where the `greybox` commands (and `greybox.io.configure_jax`) keep compiled programs
(`greybox/io/_jax_setup.py`).

That a fit whose programs come from the cache gives the same numbers to the bit as one that
compiled them, and that the command writes the cache at all, is checked by the smoke run of
benchmarks/rerun.py (tests/test_benchmarks_smoke.py: two `greybox fit` processes).
"""

import os
from pathlib import Path

import jax
import platformdirs

from greybox.io import _jax_setup
from greybox.io._atomic import can_make


def test_the_default_folder_is_the_users_cache_folder():
    folder = _jax_setup.cache_folder({})
    assert folder == Path(platformdirs.user_cache_dir("greybox", appauthor=False)) / "jax"


def test_the_environment_turns_it_off_or_moves_it(tmp_path):
    for off in ("off", "0", "no", "false", "OFF", " off "):
        assert _jax_setup.cache_folder({"GREYBOX_COMPILE_CACHE": off}) is None
    chosen = _jax_setup.cache_folder({"GREYBOX_COMPILE_CACHE": str(tmp_path / "c")})
    assert chosen == tmp_path / "c"


def test_a_folder_that_cannot_be_made_is_skipped_and_none_is_made_beforehand(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert not can_make(blocker / "jax")
    assert not can_make(blocker)
    assert can_make(tmp_path / "new" / "jax")
    assert not (tmp_path / "new").exists()  # JAX makes it at its first compile
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    assert can_make(locked / "jax") == os.access(locked, os.W_OK)  # root may write


def test_a_cache_jax_already_has_is_left_as_it_is(tmp_path):
    # the test session's own cache (tests/conftest.py), as JAX_COMPILATION_CACHE_DIR would be
    before = jax.config.jax_compilation_cache_dir
    assert before
    environ = {"GREYBOX_COMPILE_CACHE": str(tmp_path / "elsewhere")}
    assert _jax_setup.configure(environ) == Path(before)
    assert jax.config.jax_compilation_cache_dir == before
    assert not (tmp_path / "elsewhere").exists()
    assert jax.config.jax_enable_x64


def _fresh_process(code: str, *args: str, environ=None) -> str:
    """The output of `code` in a fresh interpreter (as a Dask worker or a user's script
    starts), without the test session's compile cache, with `environ` added."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "GREYBOX_TEST"))}
    out = subprocess.run(
        [sys.executable, "-c", code, *args],
        env={**env, **(environ or {})},
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return out.stdout.strip()


_WORKER = """
import sys, jax
from greybox._estimate.distributed import _use_compile_cache
_use_compile_cache({"jax_compilation_cache_dir": sys.argv[1],
                    "jax_persistent_cache_min_compile_time_secs": 0.0,
                    "jax_compilation_cache_max_size": -1})
print(jax.config.jax_compilation_cache_dir)
jax.jit(lambda x: x * 2.0 + 1.0)(1.0).block_until_ready()
"""


def _worker(tmp_path, environ) -> str:
    """A process as a Dask worker starts, given the client's cache settings: the folder its
    compiles went to."""
    return _fresh_process(_WORKER, str(tmp_path / "client"), environ=environ)


def test_a_local_clusters_workers_compile_into_the_clients_cache(tmp_path):
    # fit_distributed's workers are new processes: with the client's folder they load what
    # an earlier worker, call or command compiled (a second call: 7.6-9.0 -> 3.6-4.3 s)
    assert _worker(tmp_path, {}) == str(tmp_path / "client")
    assert [p.name.startswith("jit_") for p in (tmp_path / "client").iterdir()] == [True]
    # a worker with a cache of its own keeps it
    own = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path / "own")}
    (tmp_path / "client").rename(tmp_path / "first")
    assert _worker(tmp_path, own) == str(tmp_path / "own")
    assert not (tmp_path / "client").exists()


def test_only_a_local_cluster_is_sent_the_clients_cache(monkeypatch):
    from greybox._estimate import distributed as dist

    sent = {}

    def run_tasks(fn, payloads, **_kw):
        sent["cache"] = payloads[0][2]
        return []

    class Client:
        def close(self):
            pass

    monkeypatch.setattr(dist, "run_tasks", run_tasks)
    monkeypatch.setattr(dist, "start_client", lambda *a, **k: (Client(), None))
    monkeypatch.setattr(dist, "plan", lambda devices, free, **kw: (1, 1, 1))
    monkeypatch.setattr(dist, "_check_on_client", lambda *a: None)  # a stand-in device
    devices = [type("D", (), {"name": "d0", "model": 0.0, "experiments": ()})()]
    for scheduler, expected in (("local", dist.compile_cache_settings()), ("tcp://x:1", {})):
        sent.clear()
        try:
            dist.fit_distributed(devices, (), scheduler=scheduler)
        except RuntimeError:  # no results came back from the stand-in cluster
            pass
        assert sent["cache"] == expected
    assert sent and dist.compile_cache_settings()["jax_compilation_cache_dir"]


_SCRIPT = """
import greybox.io
folder = greybox.io.configure_jax()
import jax
print(folder, jax.config.jax_enable_x64)
jax.jit(lambda x: x * 2.0 + 1.0)(1.0).block_until_ready()
"""


def test_a_script_sets_jax_up_as_the_commands_do(tmp_path):
    environ = {
        "GREYBOX_COMPILE_CACHE": str(tmp_path / "cache"),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",  # the lambda compiles in ms
    }
    assert _fresh_process(_SCRIPT, environ=environ).split() == [str(tmp_path / "cache"), "True"]
    assert any(p.name.startswith("jit__lambda") for p in (tmp_path / "cache").iterdir())
