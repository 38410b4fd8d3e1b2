"""How the `greybox` commands set up JAX, and how a script or notebook can do the same
(`greybox.io.configure_jax`): float64, and compiled programs kept on disk.

Compiling is much of a command's time: a model's solver the first time it is fitted in a
process, its filters, its validation. JAX can write each compiled program to a folder and
load it in the next process that compiles the same program, instead of compiling it again.
The key is the program itself with its compile options and the JAX, jaxlib and back-end
versions, so an edited device, another option or another installation compiles afresh and
never loads a stale program; a loaded program is the same binary, so the numbers are the
same to the bit. That is what the identification loop repeats: `greybox fit` a folder,
read the report, change the folder, fit again; `greybox compare`, then `greybox fit` and
`greybox simulate` of the preferred structure. Measured (benchmarks/rerun.py, 2-core CPU,
2026-11-29, medians of two alternating runs): `greybox fit` of the demo folder
7.1 -> 5.2 s, chevron_process (process noise) 15.1 -> 10.4 s, microrobot 15.6 -> 12.0 s,
the same params.json numbers; the first run, which writes, costs what it did without. A
fit whose time is its solves gains little (experiments/heating_system: 49.4 s, 49.9 s).
Programs with a host callback are never written by JAX: diffrax's checks of its inputs make
the adaptive and stiff solvers' programs such, so a device fitted with `method = "adaptive"`
compiles its solver in every process.

The command turns the cache on (`configure`) in `<user cache folder>/greybox/jax` (from
`platformdirs`: ~/.cache on Linux, ~/Library/Caches on macOS, %LOCALAPPDATA% on Windows),
bounded to `CACHE_MAX_BYTES` (JAX evicts the least recently used programs; its eviction
needs `filelock`), except where

- `GREYBOX_COMPILE_CACHE` is `off` (or `0`, `no`, `false`): no cache; or a folder: that one;
- JAX already has a cache folder (`JAX_COMPILATION_CACHE_DIR`, or a program that set
  `jax_compilation_cache_dir` before calling `greybox.cli.main` or `configure_jax`): left
  as it is;
- the folder cannot be made or written: the command compiles as it would without a cache.

An entry JAX cannot read (one left half-written when the machine stopped) costs a warning and
a compile of that program; JAX never overwrites an entry, so deleting the folder clears it.

The library's core sets none of this (it leaves JAX's global configuration to the program
that imports it); a script or notebook turns it on by calling `greybox.io.configure_jax()`
first, before anything compiles (a fresh Python process fitting the demo folder, the cache
filled by an earlier one: first fit 2.1-2.2 -> 1.2 s, its validation 1.7-1.9 -> 0.9-1.1 s).
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "GREYBOX_COMPILE_CACHE"
OFF = ("0", "off", "no", "false")
CACHE_MAX_BYTES = 1 << 30  # 1 GiB: a structure's programs take 0.3-0.8 MB (benchmarks/rerun.py)
# programs that compiled at least this long are kept (the eager single operations a command
# runs compile in milliseconds: writing each would cost more than it saves)
MIN_COMPILE_S = 0.1


def cache_folder(environ=os.environ) -> Path | None:
    """The folder `configure` gives JAX (None: no cache), from the environment alone."""
    chosen = environ.get(CACHE_ENV, "").strip()
    if chosen.lower() in OFF:
        return None
    if chosen:
        return Path(chosen).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("greybox", appauthor=False)) / "jax"


def configure(environ=os.environ) -> Path | None:
    """float64 on, and the compilation cache (module docstring); returns the cache folder in
    use (None: none). Call before anything compiles (JAX reads the cache settings at its
    first compile); public as `greybox.io.configure_jax`."""
    import jax

    jax.config.update("jax_enable_x64", True)
    if jax.config.jax_compilation_cache_dir:  # the program's or JAX_COMPILATION_CACHE_DIR
        return Path(jax.config.jax_compilation_cache_dir)
    from greybox.io._atomic import can_make

    folder = cache_folder(environ)
    # JAX makes the folder at its first compile: a command that stops at bad input leaves none
    if folder is None or not can_make(folder):
        return None
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)  # evicts (filelock)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    return folder
