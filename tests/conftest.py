"""Test harness configuration: strict float64 numerics are set here, never by the library.

One JAX compilation cache serves the whole session: the pytest-xdist workers, and every
`greybox` command, benchmark smoke run and notebook kernel a test starts in a subprocess
(they inherit the environment). Many tests compile the same structures in different
processes; the second one then loads the executable instead of compiling it again. The cache
lives in a temporary folder made for the session and removed at its end, so no run sees
another's executables (set GREYBOX_TEST_JAX_CACHE to keep one across sessions).

What it does not share: any program that holds a host callback, which JAX never writes to the
cache ("Not writing persistent cache entry ... because it uses host callbacks"). Every fit's
solve and response do (equinox's `error_if` inside optimistix and diffrax is a
`pure_callback` under `EQX_ON_ERROR=raise`, the default), so each process compiles its own
fits. `EQX_ON_ERROR=nan` makes them cacheable but saved nothing measurable here (tracing
dominates; tests/test_benchmarks_smoke.py 107 -> 110 s CPU), and it would test another
error mode than users run, so it is not set.
"""

import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")

_OWN_CACHE = "GREYBOX_TEST_JAX_CACHE" not in os.environ and "PYTEST_XDIST_WORKER" not in os.environ
if _OWN_CACHE:  # the controlling process: the workers inherit this variable
    os.environ["GREYBOX_TEST_JAX_CACHE"] = tempfile.mkdtemp(prefix="greybox-jax-cache-")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.environ["GREYBOX_TEST_JAX_CACHE"])
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs",
    float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
)


def pytest_sessionfinish(session, exitstatus):
    if _OWN_CACHE and not hasattr(session.config, "workerinput"):
        shutil.rmtree(os.environ["GREYBOX_TEST_JAX_CACHE"], ignore_errors=True)
