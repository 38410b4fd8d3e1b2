"""Test harness configuration: strict float64 numerics are set here, never by the library."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
