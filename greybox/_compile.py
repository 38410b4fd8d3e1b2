"""How the library compiles: `jit` (equinox's `filter_jit`) and `jax_jit` (`jax.jit`), both
with the XLA options that keep compile time down.

Compiling is most of a first fit's time, of a `greybox compare` of new structures and of the
test suite. XLA's CPU back end emits its fused loops through its newer MLIR "fusion
emitters" by default; its older LLVM emitters compile greybox's programs in a little over
half the time (the chevron fit: XLA compile 2.3-2.9 -> 1.3-1.6 s, the first fit 2.5-2.9 ->
1.6-2.0 s), and the compiled code runs about as fast (the Kalman likelihood's gradient and
ARMAX a little faster, the Levenberg-Marquardt solve 10-20 % slower; the batch solver, which
runs long once compiled, keeps the default: `jit(fast_compile=False)`). The option is one of
XLA's per-compilation options, not a process-wide setting, and an XLA that does not know it
refuses it with an error (where an unknown XLA_FLAGS entry aborts the process), so it is
probed once (`compiler_options`) and left out where it is refused. It concerns the CPU back
end; accelerators ignore it.
"""

from __future__ import annotations

import functools
import threading

import equinox as eqx
import jax

FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False}
_TRACER = getattr(jax.core, "Tracer", ())  # () where JAX hides it: the error path below serves


@functools.cache
def compiler_options() -> dict:
    """`FAST_COMPILE` where this XLA accepts it (one trivial compile, the first time any of
    greybox's functions compiles), else no options."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=FAST_COMPILE).lower(0.0).compile()
    except Exception:  # noqa: BLE001 (an XLA that refuses the option compiles with its defaults)
        return {}
    return dict(FAST_COMPILE)


def _lazily(fun, make, fast_compile: bool):
    """`fun` compiled by `make(options)`, made at the first call (probing the options needs a
    back end, which importing greybox must not start). Called inside another function being
    traced (as the Kalman filter's `discretise` is), it is `make({})`: JAX takes compile
    options on the outermost function only, and there the outer one's apply."""
    lock, made = threading.Lock(), []

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if not made:
            with lock:
                if not made:
                    made.extend([make(compiler_options() if fast_compile else {}), make({})])
        top, nested = made
        if any(isinstance(x, _TRACER) for x in jax.tree.leaves((args, kwargs))):
            return nested(*args, **kwargs)
        try:
            return top(*args, **kwargs)
        except ValueError as e:  # traced inside another function with only constants
            if "compiler_options" not in str(e):
                raise
            return nested(*args, **kwargs)

    return call


def jit(fun=None, *, fast_compile: bool = True, **jit_kwargs):
    """`eqx.filter_jit(fun, **jit_kwargs)` with `compiler_options()`; `@jit` or `@jit(...)`.
    `fast_compile=False` keeps XLA's default code generation, for a program that runs for
    long once compiled (the batch solver: its solves were 18-33 % slower compiled fast, a
    batch's compile is shared by all its devices)."""
    if fun is None:
        return functools.partial(jit, fast_compile=fast_compile, **jit_kwargs)
    body = _traced_once(fun)
    make = lambda o: eqx.filter_jit(body, compiler_options=o, **jit_kwargs)  # noqa: E731
    return _lazily(fun, make, fast_compile)


def _traced_once(fun):
    """`fun` traced with JAX's abstract mesh set to the empty one, where none is set.

    JAX keys its cache of traced functions on its tracing context, whose abstract mesh is
    unset (None) when a function is traced from Python but the empty mesh when a jaxpr is
    evaluated again (each equation restores the context it was traced in), as optimistix does
    when it takes the shape of a solver's first linearisation (`filter_eval_shape`). The two
    are the same mesh but different keys: every inner jitted function (diffrax's
    `diffeqsolve`, optimistix's and lineax's) was traced again for the solve itself, the
    whole simulation with its derivative twice per compile. Set once at the top, both traces
    share one key (2026-11-29, first fit of tests/test_stiff_method.py's plate: tracing 4.5 ->
    2.8 s, lowering 0.57 -> 0.32 s; the same programs)."""

    @functools.wraps(fun)
    def body(*args, **kwargs):
        if not jax.sharding.get_abstract_mesh().empty:  # a mesh of the caller's: theirs
            return fun(*args, **kwargs)
        with jax.sharding.use_abstract_mesh(_EMPTY_MESH):
            return fun(*args, **kwargs)

    return body


_EMPTY_MESH = jax.sharding.AbstractMesh((), ())


def jax_jit(fun=None, **jit_kwargs):
    """`jax.jit(fun, **jit_kwargs)` with `compiler_options()` (static argument names and
    Python scalars traced as `jax.jit` does); `@jax_jit` or `@jax_jit(static_argnames=...)`."""
    if fun is None:
        return functools.partial(jax_jit, **jit_kwargs)
    body = _traced_once(fun)
    return _lazily(fun, lambda o: jax.jit(body, compiler_options=o, **jit_kwargs), True)
