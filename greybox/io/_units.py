"""File units -> SI, through pint: ``degC``, ``K``, ``degF``, ``mW``, ``W``, ``um``, ``nm``,
``%``/``pct``, ``s``, ``ms``, ... (any unit pint knows with the channel's dimension).

A channel's own unit table (`Channel.units`: ``T1_C``, ``laser_mW``, ``y_px``) is consulted
first, so every historic column name keeps its meaning (``C`` is degrees Celsius there, not
pint's coulomb); pixels (``px``) are converted with the camera scale, never by pint. A unit
of the wrong dimension (``T1_mW``) or one pint does not know is refused with the units that
would work.
"""

from __future__ import annotations

import functools

from greybox._model.channels import PIXELS, Channel

# Spellings pint would read differently (pct = picocarat) or not at all; checked first.
ALIASES = {"pct": "percent", "%": "percent", "percent": "percent", "sec": "s", "secs": "s"}
# What a message offers as examples, by SI unit of the channel.
EXAMPLES = {
    "K": ("degC", "K", "degF"),
    "W": ("mW", "W"),
    "m": ("um", "nm", "mm", "m"),
    "%": ("pct", "%"),
    "s": ("s", "ms"),
}


@functools.cache
def registry():
    import pint

    return pint.UnitRegistry(autoconvert_offset_to_baseunit=False)


def _pint_unit(text: str):
    text = ALIASES.get(text, text)
    return registry().parse_units(text)


def conversion(unit: str, si_unit: str) -> tuple[float, float]:
    """(scale, offset) with ``si = scale * value + offset`` for a value in `unit`.

    Raises `ValueError` (what is wrong, for a message) for an unknown unit or one of another
    dimension than `si_unit`."""
    if not isinstance(unit, str) or not unit.strip() or len(unit) > 40:
        raise ValueError(f"{unit!r} is not a unit")
    if unit.strip() == si_unit:  # the SI unit itself (`t_s`, `T_K`): no need to load pint
        return 1.0, 0.0  # (importing it and building its registry: ~0.5 s of a command)
    try:
        src = _pint_unit(unit.strip())
    except Exception:  # pint raises several kinds (undefined, syntax, ...)
        raise ValueError(f"unknown unit {unit!r}") from None
    try:
        dst = _pint_unit(si_unit)
    except Exception:
        raise ValueError(f"the channel's SI unit {si_unit!r} is not a unit pint knows") from None
    if src.dimensionality != dst.dimensionality:
        raise ValueError(f"{unit!r} is not a unit of {si_unit} ({src.dimensionality})")
    if "delta_" in str(src) and "delta_" not in str(dst):
        # pint converts a difference (27 delta_degC = 27 K) where a reading is absolute
        raise ValueError(
            f"{unit!r} is a unit of temperature differences, but the column holds absolute "
            f"readings; write it in {', '.join(EXAMPLES.get(si_unit, (si_unit,)))}"
        )
    q = registry().Quantity
    zero = float(q(0.0, src).to(dst).magnitude)
    one = float(q(1.0, src).to(dst).magnitude)
    return one - zero, zero


def channel_conversion(channel: Channel, unit: str) -> tuple[float, float] | None:
    """(scale, offset) to the channel's SI unit, or None for pixels (camera scale).

    The channel's own table first (historic names), then pint. `ValueError` if neither
    knows `unit` for this channel."""
    if unit in channel.units:
        return channel.units[unit]
    if unit == PIXELS:
        raise ValueError(f"{channel.name} is not measured in pixels")
    return conversion(unit, channel.si_unit)


MAX_TIME_UNIT_S = 86400.0  # a day: a lab record's time column is not kept in weeks or years


def time_conversion(unit: str) -> float:
    """Seconds per `unit` (``s``, ``ms``, ``min``, ``h``, ``day``); `ValueError` otherwise,
    also for a unit longer than a day (a year-valued time column is a wrong unit)."""
    scale, offset = conversion(unit, "s")
    if scale > MAX_TIME_UNIT_S:
        raise ValueError(
            f"{unit!r} is {scale:g} s; a lab record's times are in s, ms, min or h (at most "
            "a day per unit)"
        )
    return scale


def unit_examples(channel: Channel) -> list[str]:
    """Units to offer in a message: the channel's own, then common pint spellings."""
    out = list(channel.units)
    for u in EXAMPLES.get(channel.si_unit, (channel.si_unit,)):
        if u not in out:
            out.append(u)
    return out


def to_si(values, conv, m_per_px: float | None = None):
    """`values` converted with a `channel_conversion` result (None = pixels)."""
    if conv is None:
        if m_per_px is None:
            raise ValueError("pixel values need the camera scale (um_per_px)")
        return values * m_per_px
    scale, offset = conv
    return values * scale + offset


def from_si(values, conv, m_per_px: float | None = None):
    """Inverse of `to_si`."""
    if conv is None:
        return values / m_per_px
    scale, offset = conv
    return (values - offset) / scale
