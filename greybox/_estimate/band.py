"""What a band is: a simulated response with its pointwise band, as plain arrays.

Apart from `greybox._estimate.prediction`, which computes them, so that a process that only
draws or reads bands (the drawing process of `greybox simulate`, `greybox.io._drawing`)
unpickles one without importing JAX.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Band:
    """A simulated response with a pointwise band (SI units of the outputs).

    `y`, `lower`, `upper`, `sd_model`, `sd`: shape (N, n_y). `sd_model` is the parameter
    part, `sd` what the band uses (with noise for a prediction interval).
    """

    t_s: np.ndarray
    y: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    sd_model: np.ndarray
    sd: np.ndarray
    level: float
    includes_noise: bool

    @property
    def kind(self) -> str:
        pct = f"{self.level * 100:g} %"
        if self.includes_noise:
            return (
                f"{pct} prediction interval for new readings: parameter "
                "uncertainty (delta method) plus measurement noise sigma"
            )
        return (
            f"{pct} confidence band of the model response: parameter uncertainty only "
            "(delta method); single readings scatter further by the noise sigma"
        )


@dataclasses.dataclass(frozen=True)
class SampledBand(Band):
    """A band from sample paths (process noise), which says how it was made in `kind`."""

    description: str = ""

    @property
    def kind(self) -> str:
        return self.description
