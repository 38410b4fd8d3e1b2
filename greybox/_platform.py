"""Which kind of processor the computation being traced will run on.

The algorithms that differ between a CPU and an accelerator (the ZOH interval scan, the QR
of each Levenberg-Marquardt step) read it here. It follows `jax.default_device`, so a
`with jax.default_device(jax.devices("cpu")[0])` block on a GPU machine gets the CPU's
choices (JAX keys its compiled functions on that setting, so the two never mix)."""

from __future__ import annotations

import contextlib
import os

import equinox as eqx
import jax
import jax.numpy as jnp

_ONE_CORE = []  # non-empty while the process's own work is held to one core (`one_core`)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity, where the system tells it), or
    1 inside `one_core`."""
    if _ONE_CORE:
        return 1
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def one_core():
    """Inside, `usable_cores()` is 1: for a process that is one of many sharing the machine's
    cores (a Dask worker), whose host work (the residual tests' shuffle threads) must not
    spread over the cores the others use: 15 workers on 16 cores, each with 8 shuffle
    threads (120 threads), took 7.9 ms a device for their residual tests, where one process
    with the machine to itself took 3.7."""
    _ONE_CORE.append(True)
    try:
        yield
    finally:
        _ONE_CORE.pop()


def default_device():
    """The device computations go to: `jax.default_device`'s when one is set (a device or a
    platform name), else JAX's first device."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.devices()[0]
    return jax.devices(device)[0] if isinstance(device, str) else device


def compute_platform() -> str:
    """"cpu", "gpu", "tpu", ...: the platform of the default device in effect."""
    if jax.config.jax_default_device is None:
        return jax.default_backend()
    return default_device().platform


def on_accelerator() -> bool:
    return compute_platform() != "cpu"


def map_over_items(fn, *args, active=None):
    """`fn` over the leading axis of `args` (arrays or PyTrees of arrays), inside a compiled
    function: vmapped on an accelerator, one item after another (`lax.map`) on a CPU. A
    vmapped chunk of iterative solves runs every item for as many passes as its slowest
    needs (chevron Levenberg-Marquardt chunks: at most ~30 steps against a median of 11),
    which a CPU pays in full and barely gains back by vectorising: 512 chevron solves in
    chunks of 64 took 0.93 s mapped against 1.68 s vmapped on 2 cores. An accelerator
    needs the vectorised form; there the same chunk is one set of kernels.

    `active` (optional, one bool per item): False marks a padding item. On a CPU its `fn` is
    skipped (a branch around `fn`'s jaxpr, traced once) and its outputs are zeros, so padding
    a chunk up to one fixed size costs nothing and chunks of every batch share one compiled
    function. An accelerator ignores it: vmapped, a branch computes both sides, so padding
    items run like the others there (pad with copies of real items)."""
    if on_accelerator():
        return jax.vmap(fn)(*args)
    if active is None:
        return jax.lax.map(lambda item: fn(*item), args)
    traced = eqx.filter_closure_convert(fn, *jax.tree.map(lambda x: x[0], args))

    def skipped(*_):
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), traced.out_struct)

    def run(*xs):  # a plain function: `lax.cond` hashes its branches, a Module is unhashable
        return traced(*xs)

    def one(item):
        *xs, is_active = item
        return jax.lax.cond(is_active, run, skipped, *xs)

    return jax.lax.map(one, (*args, active))
