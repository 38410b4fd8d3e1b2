"""pint quantities at the API boundary: converted to SI, never stripped.

numpy silently drops a pint unit (`np.asarray(Q_(5, "um"))` is 5, taken as 5 m), so every
array the library accepts passes through `si_magnitude` first: a `Quantity` becomes its SI
magnitude (um -> m, ms -> s, mW -> W, degC -> K) or is refused with a clear error; any
other value is returned as given. pint is imported only when a quantity is passed.
"""

from __future__ import annotations

import numpy as np


def is_quantity(value) -> bool:
    return type(value).__module__.split(".")[0] == "pint" and hasattr(value, "magnitude")


def si_magnitude(value, what: str, dimension: str | None = None):
    """`value` in SI base units if it is a pint `Quantity` (checked against `dimension`,
    e.g. "[time]"), else `value` unchanged. A dimensionless quantity (a %) is refused:
    greybox keeps levels in the channel's own unit (50 % is 50, where pint would give 0.5)."""
    if not is_quantity(value):
        return value
    if dimension is not None and not value.check(dimension):
        raise ValueError(
            f"{what}: a quantity in {value.units:~} is not a {dimension.strip('[]')}; give "
            f"it in a unit of {dimension.strip('[]')}"
        )
    if value.dimensionless:
        raise ValueError(
            f"{what}: a dimensionless quantity ({value.units:~}) is ambiguous (greybox keeps "
            "levels in the channel's unit: 50 % is 50, pint's 0.5); pass plain numbers"
        )
    try:
        return np.asarray(value.to_base_units().magnitude, dtype=float)
    except Exception as err:  # pint's offset-unit and dimensionality errors
        raise ValueError(f"{what}: cannot convert {value.units:~} to SI ({err})") from None
