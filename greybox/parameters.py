"""Parameter tables: nominal values, units, plausible ranges and what the data can identify.

A device module publishes a tuple of `ParameterInfo` (what each field means physically) and a
default list of `greybox.fit.FreeParameter` (what a standard fit frees). Paths are dotted
attribute paths into the model PyTree, e.g. ``"thermal.tau_s"``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class ParameterInfo:
    path: str
    unit: str
    nominal: float
    lower: float | None
    upper: float | None
    description: str
    identifiability: str = ""


def getter(path: str) -> Callable:
    """A function model -> the field at dotted `path` (for `eqx.tree_at`)."""
    names = path.split(".")

    def get(model):
        obj = model
        for name in names:
            obj = getattr(obj, name)
        return obj

    return get


def get_value(model, path: str):
    try:
        return getter(path)(model)
    except AttributeError as err:
        raise ValueError(
            f"parameter path {path!r}: not a field of {type(model).__name__} "
            f"({err}); check the spelling against the model's parameter table"
        ) from None


def set_values(model, paths, values):
    """A copy of `model` with each dotted path replaced by the matching value (jit-safe)."""
    if not paths:
        return model
    getters = [getter(p) for p in paths]
    converted = [jnp.asarray(v, dtype=float) for v in values]
    return eqx.tree_at(lambda m: [g(m) for g in getters], model, converted)


def with_overrides(model, overrides: dict):
    """`model` with keyword overrides applied: ``thermal__tau_s=0.05`` sets ``thermal.tau_s``
    (what every device module's ``default_model(**overrides)`` accepts)."""
    if not overrides:
        return model
    return set_values(model, [k.replace("__", ".") for k in overrides], list(overrides.values()))
