"""Parameter tables: nominal values, units, plausible ranges and what the data can identify.

A device module publishes a tuple of `ParameterInfo` (what each field means physically) and a
default list of `greybox._estimate.fit.FreeParameter` (what a standard fit frees). Paths are dotted
attribute paths into the model PyTree, e.g. ``"thermal.tau_s"``.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class ParameterInfo:
    """One row of a device's parameter table (SI units).

    - `lower`, `upper`: the optimiser's bounds when the parameter is freed by its path alone
      (wide enough for devices of its class, not one unit's values).
    - `physical`: (lower, upper) physical range for the device's material and geometry (None
      on a side: unbounded); a fitted value outside it is flagged as implausible and a setting
      outside it is refused (`greybox._model.plausibility`; ``[physical_ranges]`` in experiment.toml
      overrides it). None: the same as (`lower`, `upper`).
    """

    path: str
    unit: str
    nominal: float
    lower: float | None
    upper: float | None
    description: str
    identifiability: str = ""
    physical: tuple[float | None, float | None] | None = None

    @property
    def physical_range(self) -> tuple[float | None, float | None]:
        return self.physical if self.physical is not None else (self.lower, self.upper)


_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")


def getter(path: str) -> Callable:
    """A function model -> the field at dotted `path` (for `eqx.tree_at`); an element of a
    tuple-valued field is named with an index, ``thermal.capacity_J_per_K[1]``."""
    steps = []
    for part in path.split("."):
        m = _STEP.match(part)
        if m is None:
            raise ValueError(
                f"parameter path {path!r}: {part!r} is not a field name (letters, digits, '_', "
                "optionally followed by [index])"
            )
        steps.append((m.group(1), [int(i) for i in re.findall(r"\d+", m.group(2))]))

    def get(model):
        obj = model
        for name, indices in steps:
            obj = getattr(obj, name)
            for i in indices:
                obj = obj[i]
        return obj

    return get


def get_value(model, path: str):
    try:
        return getter(path)(model)
    except (AttributeError, IndexError, TypeError) as err:
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


def check_scalar_path(model, path: str) -> float:
    """The value at `path` if it is a free-able scalar field; a ValueError saying why not.

    Static (structural) fields cannot be set by value: they choose the structure and are set
    through the device's options. Array-valued fields are freed element by element.
    """
    value = get_value(model, path)
    try:
        eqx.tree_at(getter(path), model, 0.0)
    except (TypeError, ValueError):
        raise ValueError(
            f"parameter path {path!r}: a structural (static) field of "
            f"{type(model).__name__}, not a parameter value; choose it through the "
            "device's [model] options"
        ) from None
    if not eqx.is_array_like(value) or isinstance(value, bool):
        raise ValueError(
            f"parameter path {path!r}: holds a {type(value).__name__}, not a number; name a "
            "numeric field"
        )
    if jnp.ndim(value) != 0:
        raise ValueError(
            f"parameter path {path!r}: holds {jnp.size(value)} values, not one; name one "
            f"element, e.g. {path}[0]"
        )
    return float(value)
