"""`Posterior`: what a fit established about a model's parameters, in one object.

A fit returns it (`FitResult.posterior`) and loading ``params.json`` returns the same thing
(`greybox.io.load_params(...).posterior`), so everything downstream (prediction bands,
parameter draws, experiment design) takes one object whether the fit ran a second ago or
months ago: the model at its fitted shared values, the free-parameter specs, the raw
(transformed) estimate, its covariance, the directions nothing determined, the noise scale per
output and the simulation method the fit used (which every prediction must use too).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Posterior:
    """- `model`: the device with the shared free parameters at their fitted values;
    - `free`: the `FreeParameter`s in the order of `raw` (shared first, then per-run blocks);
    - `raw`, `covariance_raw`: the raw estimate and its (headline) covariance;
    - `null_directions`: (k, n_raw) raw directions the data did not determine;
    - `sigma`: noise sd per output [SI]; `method`: the simulation path of the fit;
    - `noise`: the fit's noise-model object (`model` is a `StochasticDevice` for
      `ProcessNoise`);
    - `solver`: the adaptive solver's settings the fit simulated with (`solver_rtol`,
      `solver_atol`, `solver_max_steps`; empty: the defaults), which its bands use too.
    """

    model: object
    free: tuple
    raw: np.ndarray
    covariance_raw: np.ndarray
    null_directions: np.ndarray
    sigma: np.ndarray
    method: str
    noise: object = None  # the fit's noise model (OutputError / ProcessNoise)
    solver: dict = dataclasses.field(default_factory=dict)

    def band(self, inputs, t_s, *, noise: bool = False, level: float = 0.95, t_start_s=0.0):
        """The response to `inputs` at `t_s` with its pointwise band (`greybox.Band`): a
        confidence band of the model response, or with `noise` a prediction interval.

        With process noise (`model` a `StochasticDevice`: a `ProcessNoise` fit) the band is
        that of sample paths (`greybox._estimate.prediction.process_band`): process noise and
        parameter draws, with `noise` measurement noise too; its `kind` says so."""
        from greybox._estimate.fit import simulate_settings
        from greybox._estimate.prediction import prediction_band, process_band
        from greybox.stochastic._sde_device import StochasticDevice

        if isinstance(self.model, StochasticDevice):
            return process_band(
                self.model,
                self.free,
                self.raw,
                self.covariance_raw,
                inputs,
                t_s,
                measurement_noise=noise,
                level=level,
                t_start_s=t_start_s,
            )

        return prediction_band(
            self.model,
            self.free,
            self.raw,
            self.covariance_raw,
            inputs,
            t_s,
            sigma=self.sigma if noise else None,
            null_directions=self.null_directions,
            level=level,
            method=self.method,
            t_start_s=t_start_s,
            **simulate_settings(self.solver),
        )

    def draws(self, n: int, *, seed: int = 0) -> np.ndarray:
        """`n` Gaussian draws (n, n_shared) of the shared raw coordinates."""
        from greybox._estimate.prediction import raw_draws

        return raw_draws(self.raw, self.covariance_raw, self.free, n, seed=seed)
