"""`Experiment`: one recorded run in SI units (arrays only; loading files is `greybox.io`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from greybox._model.waveforms import PiecewiseConstant


def check_times(t_s, name: str = "t_s") -> np.ndarray:
    """Frame times [s] as a float array, refused unless finite and strictly increasing."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    if t.size == 0:
        raise ValueError(f"{name}: no timestamps; give at least one frame time [s]")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: timestamps contain NaN; remove those frames")
    if np.any(np.diff(t) <= 0):
        bad = int(np.argmax(np.diff(t) <= 0))
        raise ValueError(
            f"{name}: timestamps must be strictly increasing (frame {bad + 1} at "
            f"{t[bad + 1]} s follows {t[bad]} s); sort them and drop duplicates"
        )
    return t


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One run: the input waveform and the camera readings.

    - `name`: label used in reports.
    - `t_s`: frame timestamps [s], shape (N,), strictly increasing, any spacing.
    - `y`: readings in SI (m for displacement, K or degC for temperatures), shape (N,) or
      (N, n_y); NaN marks a dropped or untrackable frame (masked out, never interpolated).
    - `inputs`: input waveform in the device's SI input units (W for laser power).
    - `t_start_s`: time [s] at which the device is in its initial state.
    - `role`: "estimation" or "validation".
    - `settings`: known per-run model values {dotted path: SI value} applied on top of the
      model for this run only (e.g. an initial temperature, a spot position); never fitted.
    - `sigma`: known measurement noise sd per frame in the units of `y` (SI), shape (N,) (one
      level for every output) or (N, n_y); None when unknown. `fit` then weights each
      reading by it, does not re-estimate the noise, and tests the fit against it.

    `t_s`, `y`, `sigma` and settings may be pint quantities (``Q_(y, "um")``): they are
    converted to SI base units (um -> m, ms -> s, degC -> K), or refused when
    dimensionless or of the wrong dimension; numpy alone would strip the unit. A pandas
    DataFrame is read with `greybox.io.experiment_from_dataframe`.
    """

    name: str
    t_s: np.ndarray
    y: np.ndarray
    inputs: PiecewiseConstant
    t_start_s: float = 0.0
    role: str = "estimation"
    settings: dict = dataclasses.field(default_factory=dict)
    sigma: np.ndarray | None = None

    def __post_init__(self):
        from greybox._model.quantities import si_magnitude

        # pint quantities become SI numbers here (numpy alone would strip the unit)
        t = check_times(
            si_magnitude(self.t_s, f"{self.name}: t_s", "[time]"), name=f"{self.name}: t_s"
        )
        y = np.asarray(si_magnitude(self.y, f"{self.name}: y"), dtype=float)
        if self.sigma is not None:
            object.__setattr__(self, "sigma", si_magnitude(self.sigma, f"{self.name}: sigma"))
        object.__setattr__(
            self,
            "settings",
            {
                k: si_magnitude(v, f"{self.name}: setting {k}")
                for k, v in dict(self.settings).items()
            },
        )
        if y.ndim == 1:
            y = y[:, None]
        if y.shape[0] != t.size:
            raise ValueError(
                f"{self.name}: y has {y.shape[0]} samples but t_s has {t.size}; lengths must match"
            )
        finite = np.isfinite(y)
        if not finite.any():
            raise ValueError(f"{self.name}: y is NaN in every frame; nothing to fit")
        if np.isinf(y).any():
            raise ValueError(f"{self.name}: y contains infinite values; mark bad frames as NaN")
        if self.role not in ("estimation", "validation"):
            raise ValueError(
                f"{self.name}: role {self.role!r} must be 'estimation' or 'validation'"
            )
        if not np.all(np.isfinite(np.asarray(self.inputs.values))):
            raise ValueError(f"{self.name}: inputs contain NaN or infinite levels")
        for path, value in self.settings.items():
            if not np.all(np.isfinite(np.asarray(value, dtype=float))):
                raise ValueError(f"{self.name}: setting {path} = {value!r} is not a finite number")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "y", y)
        if self.sigma is not None:
            sigma = np.asarray(self.sigma, dtype=float)
            if sigma.ndim == 1:
                sigma = sigma[:, None]
            if sigma.ndim != 2 or sigma.shape[0] != t.size or sigma.shape[1] not in (1, y.shape[1]):
                raise ValueError(
                    f"{self.name}: sigma has shape {np.shape(self.sigma)}; give one noise sd per "
                    f"frame, shape ({t.size},) or ({t.size}, {y.shape[1]})"
                )
            sigma = np.broadcast_to(sigma, y.shape).copy()
            bad = finite & ~(np.isfinite(sigma) & (sigma > 0))
            if bad.any():
                frame = int(np.argwhere(bad)[0, 0])
                raise ValueError(
                    f"{self.name}: sigma must be finite and > 0 at every valid frame "
                    f"(frame {frame} has {sigma[bad][0]!r}); NaN is allowed only where y is NaN"
                )
            object.__setattr__(self, "sigma", sigma)

    def input_onset_s(self) -> float:
        """Time [s] at which the input first leaves zero (inf if it never does)."""
        levels = np.asarray(self.inputs.values).reshape(len(self.inputs.times_s), -1)
        on = self.inputs.times_s[np.any(levels != 0, axis=1)]
        return float(on[0]) if on.size else float("inf")

    def rest_level(self, min_frames: int = 3) -> np.ndarray:
        """(n_y,) median reading of each output before the input first switches on.

        The rest position of a shuttle in the image, i.e. its camera offset; NaN for an output
        with fewer than `min_frames` valid frames before the onset.
        """
        before = self.t_s < self.input_onset_s()
        out = np.full(self.y.shape[1], np.nan)
        for j in range(self.y.shape[1]):
            vals = self.y[before, j]
            vals = vals[np.isfinite(vals)]
            if vals.size >= min_frames:
                out[j] = np.median(vals)
        return out

    @property
    def n_frames(self) -> int:
        return self.t_s.size

    def apply_settings(self, model):
        """`model` with this run's known settings applied."""
        from greybox._model.parameters import set_values

        return set_values(model, list(self.settings), list(self.settings.values()))

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self.y)

    def frame_inputs(self) -> np.ndarray:
        """The input levels at the frames, (N, n_u) in the inputs' SI units (read-only:
        evaluated once, as a fit's residual tests and its sandwich both ask for them)."""
        levels = self.__dict__.get("_frame_inputs")
        if levels is None:
            levels = np.array(self.inputs(self.t_s), dtype=float).reshape(self.n_frames, -1)
            levels.setflags(write=False)
            object.__setattr__(self, "_frame_inputs", levels)
        return levels
