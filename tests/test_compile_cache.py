"""Where the `greybox` command keeps compiled programs (`greybox/cli/_jax_setup.py`).

That a fit whose programs come from the cache gives the same numbers to the bit as one that
compiled them, and that the command writes the cache at all, is checked by the smoke run of
benchmarks/rerun.py (tests/test_benchmarks_smoke.py: two `greybox fit` processes).
"""

import os
from pathlib import Path

import jax
import platformdirs

from greybox.cli import _jax_setup
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
