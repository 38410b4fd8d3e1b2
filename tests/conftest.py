"""Test harness configuration: strict float64 numerics are set here, never by the library.

One JAX compilation cache serves the whole session: the pytest-xdist workers, and every
`greybox` command, benchmark smoke run and notebook kernel a test starts in a subprocess
(they inherit the environment). Many tests compile the same structures in different
processes; the second one then loads the executable instead of compiling it again. The cache
lives in a temporary folder made for the session and removed at its end, so no run sees
another's executables (set GREYBOX_TEST_JAX_CACHE to keep one across sessions).

What it does not share: a program that holds a host callback, which JAX never writes to the
cache ("... because it uses host callbacks"): equinox's `error_if` (a `pure_callback` under
`EQX_ON_ERROR=raise`, the default) where a solve keeps one. Since the solvers run with
`throw=False` that is a few programs only (in tests/test_fit.py, test_stochastic_device.py,
test_simulate.py, test_kalman.py and test_microrobot.py together: one `_solve`, four
`_observe_jit` and four lambdas); the output-error `_solve`, the likelihood's
`_newton` and the filters are cached (a chevron fit in a second process: 2.4 -> 1.0 s). Most
of the suite's compile time is still spent: its tests compile different structures, so
little is compiled twice (tests/test_fit.py, test_process_engine.py,
test_stochastic_device.py and test_cli_process.py: 145 s of XLA compilation, 3.7 s of it
saved by the cache). `EQX_ON_ERROR` is not set to `nan`: it would test another error mode
than users run.
"""

import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
# one OpenBLAS thread a process (the workers, and every notebook kernel, benchmark smoke run
# and command they start inherit it): the suite runs a process per core, and OpenBLAS's
# threads wait for work by spinning, on the core the other process needs. perf over the
# whole suite on a 2-core machine: 23 s of CPU in numpy's and scipy's OpenBLAS threads
# waiting (`blas_thread_server`, `exec_blas_async_wait`), against ~3 s of their arithmetic;
# with one thread the suite took 242 s (user + sys CPU 468 s), against 254-260 s (490-501 s)
# the same hour. A value already set is left as it is.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# For the same reason, one thread in XLA's CPU pool (it runs the compiled programs and waits
# for work by spinning too: 12 s of the suite's CPU in `GlobalSteal` and `PopBack`). XLA
# sizes the pool from PJRT_NPROC where it is set (`DefaultThreadPoolSize`, the knob by which
# Google's CI reserves cores for a test), else from the cores. Two compile-heavy test files
# in one process: CPU 46.0 -> 39.8 s, spinning 1.45 -> 0.03 s; the suite: 233-248 s (CPU
# 451-480 s) -> 221.5-232.0 s (430-448 s), a fresh clone with the README's command 228.1 s.
os.environ.setdefault("PJRT_NPROC", "1")

# full collections rarer (after 100 collections of the middle generation, not 10): a
# worker's heap grows with every compiled program (the jaxprs and executables JAX keeps),
# and each full collection walks all of it (31 a worker, 0.4 s each: 25 s of the suite's CPU;
# with this 9-11 a worker, 12.5 s). Young collections rarer too (after 10,000 net
# allocations, not 700): tracing makes millions of short-lived objects, few of them in
# cycles (tests/test_stochastic_device.py and test_electrothermal.py in one process: 2,575
# collections taking 1.2 s -> 305 taking 0.53 s)
gc.set_threshold(10_000, 10, 100)

_OWN_CACHE = "GREYBOX_TEST_JAX_CACHE" not in os.environ and "PYTEST_XDIST_WORKER" not in os.environ
if _OWN_CACHE:  # the controlling process: the workers inherit this variable
    os.environ["GREYBOX_TEST_JAX_CACHE"] = tempfile.mkdtemp(prefix="greybox-jax-cache-")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.environ["GREYBOX_TEST_JAX_CACHE"])
# every program, however quick to compile: the many small ones (observation maps, filters)
# are what the subprocesses, notebook kernels and the other worker compile again (suite on a
# quiet 2-core machine: 316 and 318 s with 0.3 s here, 303 s with 0)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# the tests check numbers, not speed: XLA's CPU back end compiles with LLVM at optimisation
# level 0, the same programs (same HLO passes, no fast math at any level) in less time, and
# what the suite compiles outweighs what it runs (on a quiet 2-core machine: 311 -> 267-290
# s, CPU 568 -> 504-528 s; a long-running solve runs ~1.5x slower, a micro-robot fit 3.5 ->
# 5.2 s warm). Results differ from an optimised build by rounding only (the demo folder's
# estimates by 7e-16 relative, the TCLab one-heater fit's by 7e-11, the micro-robot's
# prior-dominated friction and stiffness by up to 4e-9, as their solves amplify it), which
# every test's tolerance allows. A level already in XLA_FLAGS is left as it is.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    ).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs",
    float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
)

# For the same reason, every program (greybox's batch solver, which keeps XLA's default code
# generation for its long runs, and the tests' own jitted functions included) is built with
# XLA's older LLVM emitters, as greybox's other functions are (`greybox/_compile.py`), and
# as one LLVM module rather than several compiled in parallel threads (on two busy cores the
# split only adds work). Suite on a 2-core machine (with the level above): 259 s (user CPU
# 478 s) -> 239 s with the emitters alone (444 s) -> 224-229 s with both (415-422 s).
# Each is an XLA_FLAGS entry only where this XLA knows it (an unknown entry would abort
# every process): probed once, as a compile option of a trivial program, in the process
# that starts the session (the workers and subprocesses inherit the environment).
_BUILD = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_parallel_codegen_split_count": 1}


def _xla_knows(name: str, value) -> bool:
    """Whether this XLA takes `name` as a compile option (then also as an XLA_FLAGS entry)."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options={name: value}).lower(0.0).compile()
    except Exception:  # noqa: BLE001 (refused: this XLA has no such option)
        return False
    return True


for _name, _value in _BUILD.items():
    if _name not in os.environ["XLA_FLAGS"] and _xla_knows(_name, _value):
        os.environ["XLA_FLAGS"] += f" --{_name}={str(_value).lower()}"


@pytest.hookimpl(tryfirst=True)
def pytest_unconfigure(config):
    # the session is over: pytest's last garbage collection (a check for unraisable
    # exceptions, after every test's own) would walk every object a worker still holds, its
    # compiled programs' above all (1.3 million objects after five test files: 0.75 s; a
    # worker ends the suite with several times that); frozen, they are not walked
    gc.freeze()


def pytest_sessionfinish(session, exitstatus):
    if _OWN_CACHE and not hasattr(session.config, "workerinput"):
        shutil.rmtree(os.environ["GREYBOX_TEST_JAX_CACHE"], ignore_errors=True)
