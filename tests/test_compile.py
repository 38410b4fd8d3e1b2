"""greybox/_compile.py: the library's compiled functions give the closed form wherever they are
called (alone, inside another compiled function, under vmap), and an XLA option the installed
XLA refuses is left out instead of breaking every compile."""

import jax
import jax.numpy as jnp
import numpy as np

from greybox import _compile


def test_compiled_functions_run_alone_nested_and_vmapped():
    f = _compile.jit(lambda x: jnp.sin(x) ** 2)
    outer = _compile.jax_jit(lambda x: f(x) + 1.0)  # f traced inside: no options of its own
    constants = _compile.jax_jit(lambda: f(jnp.asarray(2.0)))  # f's argument is no tracer
    x = np.linspace(-1.0, 3.0, 7)
    np.testing.assert_allclose(f(x), np.sin(x) ** 2, rtol=1e-15)
    np.testing.assert_allclose(outer(x), np.sin(x) ** 2 + 1.0, rtol=1e-15)
    np.testing.assert_allclose(constants(), np.sin(2.0) ** 2, rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(f)(x), np.sin(x) ** 2, rtol=1e-15)
    np.testing.assert_allclose(jax.grad(f)(0.7), np.sin(1.4), rtol=1e-14)  # d sin^2 = sin 2x


def test_an_option_xla_refuses_is_left_out(monkeypatch):
    monkeypatch.setattr(_compile, "FAST_COMPILE", {"xla_no_such_option_anywhere": True})
    _compile.compiler_options.cache_clear()
    try:
        assert _compile.compiler_options() == {}
        g = _compile.jit(lambda x: jnp.exp(-x) * 3.0)
        np.testing.assert_allclose(g(np.array([0.0, 1.0])), [3.0, 3.0 / np.e], rtol=1e-15)
    finally:
        _compile.compiler_options.cache_clear()  # the next caller probes the real option again
