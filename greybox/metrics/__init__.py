"""Scores and diagnostics of a fitted model: fit %, RMSE, MAE, SAE and R^2, the Ljung-Box
whiteness test of residuals, identifiability, per-run likelihood diagnostics and the scores of
compared candidate structures.

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "fit_percent": ("greybox._estimate.metrics", "fit_percent"),
    "fit_percent_per_output": ("greybox._estimate.metrics", "fit_percent_per_output"),
    "rmse": ("greybox._estimate.metrics", "rmse"),
    "mae": ("greybox._estimate.metrics", "mae"),
    "sae": ("greybox._estimate.metrics", "sae"),
    "r_squared": ("greybox._estimate.metrics", "r_squared"),
    "ljung_box": ("greybox._estimate.stochastic_fit", "ljung_box"),
    "LjungBox": ("greybox._estimate.stochastic_fit", "LjungBox"),
    "IdentifiabilityReport": ("greybox._estimate.identifiability", "IdentifiabilityReport"),
    "RunDiagnostics": ("greybox._estimate.likelihood", "RunDiagnostics"),
    "CandidateScore": ("greybox._estimate.compare", "CandidateScore"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.compare import CandidateScore as CandidateScore
    from greybox._estimate.identifiability import IdentifiabilityReport as IdentifiabilityReport
    from greybox._estimate.likelihood import RunDiagnostics as RunDiagnostics
    from greybox._estimate.metrics import fit_percent as fit_percent
    from greybox._estimate.metrics import fit_percent_per_output as fit_percent_per_output
    from greybox._estimate.metrics import mae as mae
    from greybox._estimate.metrics import r_squared as r_squared
    from greybox._estimate.metrics import rmse as rmse
    from greybox._estimate.metrics import sae as sae
    from greybox._estimate.stochastic_fit import LjungBox as LjungBox
    from greybox._estimate.stochastic_fit import ljung_box as ljung_box
