"""Device models composed from greybox blocks; one module per device.

Each module defines: `NAME`, `INPUTS` and `OUTPUTS` (tuples of `greybox.channels.Channel`),
`default_model(**overrides)`, `PARAMETERS` (tuple of `greybox.parameters.ParameterInfo`) and
`default_free_parameters()` (list of `greybox.freeparams.FreeParameter`).
"""

from __future__ import annotations

import importlib
import pkgutil


def available() -> list[str]:
    """Names of the device modules in this package."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def load(name: str):
    """The device module called `name`; a ValueError lists the known devices otherwise."""
    if name not in available():
        raise ValueError(f"device: unknown device model {name!r}; known: {', '.join(available())}")
    return importlib.import_module(f"models.{name}")
