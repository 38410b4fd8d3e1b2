"""Laser (or heater) input waveforms with exact switching times.

Every waveform is piecewise constant and knows its edges, so the ZOH path can step exactly
from edge to edge and the adaptive path can declare them as `jump_ts`: no solver ever steps
blindly across a discontinuity. Values are in SI (W for laser power) unless the channel says
otherwise (e.g. heater % of full scale for TCLab).

A waveform is data, not a fitted parameter, so these are frozen dataclasses holding numpy
arrays; `PiecewiseConstant` is the canonical form every other waveform converts to.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np


def _check_finite(name: str, values) -> np.ndarray:
    from greybox._model.quantities import si_magnitude

    dimension = "[time]" if name.endswith("_s") else None
    arr = np.asarray(si_magnitude(values, name, dimension), dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or infinite values; give finite numbers")
    return arr


@dataclasses.dataclass(frozen=True)
class PiecewiseConstant:
    """Zero-order-hold signal: ``value(t) = values[i]`` for ``times_s[i] <= t < times_s[i+1]``.

    - `times_s`: breakpoints [s], shape (m,), strictly increasing.
    - `values`: level after each breakpoint, shape (m,) for one channel or (m, c) for c channels
      (SI units of the channel, W for laser power). Before `times_s[0]` the signal is 0.
    - `end_s`: end of the record [s] (>= last breakpoint); the last level holds until then.
    """

    times_s: np.ndarray
    values: np.ndarray
    end_s: float

    def __post_init__(self):
        times = _check_finite("times_s", self.times_s).reshape(-1)
        values = _check_finite("values", self.values)
        if times.size == 0:
            raise ValueError("times_s: a waveform needs at least one breakpoint")
        if values.shape[0] != times.size:
            raise ValueError(
                f"values: has {values.shape[0]} levels but times_s has {times.size} breakpoints; "
                "give one level per breakpoint"
            )
        if np.any(np.diff(times) <= 0):
            raise ValueError(
                "times_s: breakpoints must be strictly increasing; sort them and remove duplicates"
            )
        from greybox._model.quantities import si_magnitude

        end = float(si_magnitude(self.end_s, "end_s", "[time]"))
        if not np.isfinite(end) or end < times[-1]:
            raise ValueError(f"end_s: {end} is before the last breakpoint {times[-1]}")
        object.__setattr__(self, "times_s", times)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "end_s", end)

    @property
    def n_channels(self) -> int:
        return 1 if self.values.ndim == 1 else self.values.shape[1]

    @property
    def duration_s(self) -> float:
        return self.end_s - self.times_s[0]

    def switch_times(self) -> np.ndarray:
        """Times [s] at which the level actually changes (including a jump from 0 at the start)."""
        levels = self.values.reshape(len(self.times_s), -1)
        previous = np.vstack([np.zeros((1, levels.shape[1])), levels[:-1]])
        changed = np.any(levels != previous, axis=1)
        return self.times_s[changed]

    def __call__(self, t) -> np.ndarray:
        """Level at time(s) `t` [s] (right-continuous; 0 before the first breakpoint)."""
        t = np.asarray(t, dtype=float)
        idx = np.searchsorted(self.times_s, t, side="right") - 1
        out = self.values[np.clip(idx, 0, None)]
        zero = (idx < 0).reshape(idx.shape + (1,) * (out.ndim - idx.ndim))
        return np.where(zero, 0.0, out)

    def to_piecewise(self) -> PiecewiseConstant:
        return self

    def shifted(self, offset_s: float) -> PiecewiseConstant:
        return PiecewiseConstant(self.times_s + offset_s, self.values, self.end_s + offset_s)

    def scaled(self, factor: float) -> PiecewiseConstant:
        """The same waveform with every level multiplied by `factor` (e.g. mW -> W)."""
        return PiecewiseConstant(self.times_s, self.values * factor, self.end_s)

    def mean(self) -> np.ndarray:
        """Time-average level over [times_s[0], end_s]."""
        widths = np.diff(np.append(self.times_s, self.end_s))
        levels = self.values.reshape(len(self.times_s), -1)
        avg = (widths[:, None] * levels).sum(axis=0) / max(self.duration_s, 1e-300)
        return avg if self.values.ndim > 1 else avg[0]


@dataclasses.dataclass(frozen=True)
class PulseTrain:
    """Square pulse train: `power_W` on for `duty * period_s` of every period.

    - `power_W`: on-level [W] (>= 0); the off-level is 0.
    - `period_s`: pulse period [s] (> 0); `duty`: on-fraction in (0, 1].
    - `delay_s`: time of the first rising edge [s]; `n_pulses`: number of pulses.
    - `tail_s`: laser-off time recorded after the last period [s].
    """

    power_W: float
    period_s: float
    duty: float = 0.5
    n_pulses: int = 10
    delay_s: float = 0.0
    tail_s: float = 0.0

    def __post_init__(self):
        checks = [
            ("power_W", self.power_W >= 0, "laser power cannot be negative"),
            ("period_s", self.period_s > 0, "the period must be positive"),
            ("duty", 0 < self.duty <= 1, "duty is the on-fraction, in (0, 1]"),
            (
                "n_pulses",
                int(self.n_pulses) == self.n_pulses and 1 <= self.n_pulses <= 10_000_000,
                "give a whole number of pulses, 1 to 10,000,000 (every edge is stored)",
            ),
            ("delay_s", self.delay_s >= 0, "the delay cannot be negative"),
            ("tail_s", self.tail_s >= 0, "the tail cannot be negative"),
        ]
        for name, ok, fix in checks:
            value = getattr(self, name)
            if not np.isfinite(value) or not ok:
                raise ValueError(f"{name}: {value!r} is invalid; {fix}")

    @property
    def duration_s(self) -> float:
        return self.delay_s + self.n_pulses * self.period_s + self.tail_s

    def to_piecewise(self) -> PiecewiseConstant:
        k = np.arange(int(self.n_pulses))
        rises = self.delay_s + k * self.period_s
        falls = rises + self.duty * self.period_s
        if self.duty >= 1.0:  # continuous on: a single step
            times, values = [rises[0]], [self.power_W]
            end_on = falls[-1]
            times, values = np.array(times + [end_on]), np.array(values + [0.0])
        else:
            times = np.column_stack([rises, falls]).reshape(-1)
            values = np.tile([self.power_W, 0.0], len(k))
        if self.delay_s > 0:
            times = np.concatenate([[0.0], times])
            values = np.concatenate([[0.0], values])
        end = max(self.duration_s, times[-1])
        return PiecewiseConstant(times, values, end)

    def switch_times(self) -> np.ndarray:
        return self.to_piecewise().switch_times()

    def __call__(self, t):
        return self.to_piecewise()(t)


def from_samples(
    times_s, values, *, end_s: float | None = None, name: str = "laser"
) -> PiecewiseConstant:
    """Piecewise-constant trace from logged samples (each sample held until the next one).

    Raises `ValueError` naming `name` for NaN or non-monotonic times (whether a level may be
    negative is the input channel's declaration, checked where files are read).
    """
    times = np.asarray(times_s, dtype=float).reshape(-1)
    vals = np.asarray(values, dtype=float)
    if times.size != vals.shape[0]:
        raise ValueError(
            f"{name}: {times.size} times but {vals.shape[0]} values; lengths must match"
        )
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{name}: logged values contain NaN; fill or remove those samples")
    if np.any(np.diff(times) <= 0):
        raise ValueError(f"{name}: sample times must be strictly increasing")
    if end_s is None:
        end_s = times[-1] + (np.median(np.diff(times)) if times.size > 1 else 0.0)
    # merge repeated levels so the edge list holds only real switches
    keep = np.ones(times.size, dtype=bool)
    flat = vals.reshape(times.size, -1)
    keep[1:] = np.any(flat[1:] != flat[:-1], axis=1)
    return PiecewiseConstant(times[keep], vals[keep], end_s)


def multilevel_prbs(
    levels_W: Sequence[float], hold_s: float, n_holds: int, *, seed: int = 0, start_s: float = 0.0
) -> PiecewiseConstant:
    """Pseudo-random multilevel sequence: every `hold_s` [s] a level drawn from `levels_W`.

    Deterministic for a given `seed`; consecutive holds may repeat a level (merged into one).
    """
    levels = np.asarray(levels_W, dtype=float)
    if levels.size < 2 or np.any(levels < 0):
        raise ValueError("levels_W: give at least two non-negative levels [W]")
    if not hold_s > 0 or n_holds < 1:
        raise ValueError("hold_s/n_holds: need hold_s > 0 and n_holds >= 1")
    rng = np.random.default_rng(seed)
    draws = levels[rng.integers(0, levels.size, size=int(n_holds))]
    times = start_s + hold_s * np.arange(int(n_holds))
    return from_samples(times, draws, end_s=start_s + hold_s * n_holds, name="levels_W")


def concatenate(waveforms: Sequence, *, gaps_s: float | Sequence[float] = 0.0) -> PiecewiseConstant:
    """Stitch waveforms end to end (as the thesis stitched six experiments into one record).

    `gaps_s` [s] is laser-off time inserted after each waveform but the last (scalar or one per
    waveform).
    """
    pieces = [w.to_piecewise() for w in waveforms]
    if not pieces:
        raise ValueError("waveforms: nothing to concatenate")
    gaps = np.broadcast_to(np.asarray(gaps_s, dtype=float), (len(pieces),))
    if np.any(gaps < 0):
        raise ValueError("gaps_s: gaps cannot be negative")
    zero = np.zeros((1,) + pieces[0].values.shape[1:])
    times, values, cursor = [], [], 0.0
    for i, piece in enumerate(pieces):
        shift = cursor - piece.times_s[0]
        times.append(piece.times_s + shift)
        values.append(piece.values)
        cursor = piece.end_s + shift
        if gaps[i] > 0 and i < len(pieces) - 1:
            times.append(np.array([cursor]))
            values.append(zero)
            cursor += gaps[i]
    t_all, v_all = np.concatenate(times), np.concatenate(values)
    # a piece whose last level has zero length would duplicate the next start: keep the later one
    keep = np.append(np.diff(t_all) > 0, True)
    return from_samples(t_all[keep], v_all[keep], end_s=cursor, name="waveforms")


def stack_channels(waveforms: Sequence) -> PiecewiseConstant:
    """Combine single-channel waveforms into one multi-channel input on merged breakpoints."""
    pieces = [w.to_piecewise() for w in waveforms]
    times = np.unique(np.concatenate([p.times_s for p in pieces]))
    values = np.column_stack([np.asarray(p(times)).reshape(times.size) for p in pieces])
    end = max(p.end_s for p in pieces)
    return PiecewiseConstant(times, values, end)
