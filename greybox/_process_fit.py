"""Adapters kept while the command line switches to `greybox.fit(noise=ProcessNoise(...))`.

`fit_process` and `validate_process` are thin wrappers over the one fit
(`greybox._likelihood`); they return the unified `FitResult` and `RunDiagnostics`. Delete this
module once greybox/cli no longer imports it (ENGINE-NOTES.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from greybox._likelihood import RunDiagnostics
from greybox._noise_models import ProcessNoise
from greybox._sde_device import DEFAULT_K_STEP

__all__ = ["ProcessFitResult", "RunDiagnostics", "fit_process", "validate_process"]


def fit_process(
    model,
    experiments: Sequence,
    free: Sequence,
    *,
    max_steps: int | None = None,
    gtol: float | None = None,
    whiteness_lags: int = 20,
    k_step: int = DEFAULT_K_STEP,
    start_noise: bool = True,
    n_starts: int | None = 1,
    progress: Callable[[str], None] | None = None,
):
    """`greybox.fit(model, experiments, free, noise=ProcessNoise(model.structure, ...))`
    (`gtol` is no longer used: the damped Newton search stops on the Newton decrement)."""
    from greybox._fit import fit

    del gtol
    noise = ProcessNoise(
        model.structure, k_step=int(k_step), whiteness_lags=int(whiteness_lags),
        start_noise=bool(start_noise),
    )
    return fit(
        model,
        experiments,
        free,
        noise=noise,
        n_starts=n_starts,
        max_steps=None if max_steps is None else min(int(max_steps), 2000),
        progress=progress,
    )


def validate_process(result, experiments, *, whiteness_lags=None, k_step=None) -> tuple:
    """`RunDiagnostics` (role "validation") of each run: `greybox.validate(result, ...).runs`."""
    import dataclasses

    from greybox._fit import validate

    if whiteness_lags is not None or k_step is not None:
        noise = dataclasses.replace(
            result.noise,
            whiteness_lags=whiteness_lags or result.noise.whiteness_lags,
            k_step=k_step or result.noise.k_step,
        )
        result = dataclasses.replace(result, noise=noise)
    return validate(result, experiments).runs


def __getattr__(name):
    if name == "ProcessFitResult":  # the one result type now
        from greybox._fit import FitResult

        return FitResult
    raise AttributeError(name)
