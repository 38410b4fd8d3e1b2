"""Synthetic camera recordings with the defects of real ones (PHYSICS.md §10).

Irregular frame times (nominal rate plus jitter), Gaussian tracking noise, dropped frames
(NaN) and a burst of corrupted frames (gross errors), generated from a device model with a
seeded numpy Generator so the truth is known exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from greybox._model.data import Experiment
from greybox._simulate.simulate import simulate


@dataclasses.dataclass(frozen=True)
class CameraDefects:
    """- `fps`: nominal frame rate [1/s]; `jitter_s`: sd of timestamp jitter [s].
    - `noise_m`: tracking-noise sd [m]; `drop_fraction`: share of frames lost (NaN).
    - `burst_length`: number of consecutive corrupted frames (0 = none), displaced by
      `burst_size_m` [m] with random sign, starting at a random frame.
    """

    fps: float = 30.0
    jitter_s: float = 2e-3
    noise_m: float = 0.05e-6
    drop_fraction: float = 0.05
    burst_length: int = 0
    burst_size_m: float = 2e-6


def frame_times(duration_s: float, defects: CameraDefects, rng: np.random.Generator) -> np.ndarray:
    n = int(np.floor(duration_s * defects.fps))
    t = (np.arange(n) + 0.5) / defects.fps + rng.normal(0.0, defects.jitter_s, n)
    t = np.sort(np.clip(t, 1e-4, duration_s))
    keep = np.append(np.diff(t) > 1e-6, True)
    return t[keep]


def record(
    model,
    inputs,
    *,
    name: str,
    defects: CameraDefects,
    seed: int,
    role: str = "estimation",
    method: str = "zoh",
) -> tuple[Experiment, np.ndarray]:
    """A synthetic run: (Experiment with noisy/dropped/corrupted readings, clean readings)."""
    rng = np.random.default_rng(seed)
    duration = inputs.to_piecewise().end_s
    t = frame_times(duration, defects, rng)
    clean = np.asarray(simulate(model, inputs, t, method=method)).reshape(t.size, -1)
    y = clean + rng.normal(0.0, defects.noise_m, clean.shape)
    if defects.burst_length > 0:
        start = int(rng.integers(0, max(t.size - defects.burst_length, 1)))
        sign = rng.choice([-1.0, 1.0])
        y[start : start + defects.burst_length] += (
            sign
            * defects.burst_size_m
            * (1.0 + rng.uniform(0, 1, (min(defects.burst_length, t.size - start), y.shape[1])))
        )
    dropped = rng.uniform(size=t.size) < defects.drop_fraction
    y[dropped] = np.nan
    return Experiment(name, t, y, inputs.to_piecewise(), role=role), clean
