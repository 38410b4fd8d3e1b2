"""A fit's parameter uncertainty carried to what you compute from the device:
prediction bands, the delta method, Monte Carlo propagation and parameter draws.

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "Posterior": ("greybox._estimate.posterior", "Posterior"),
    "Band": ("greybox._estimate.band", "Band"),
    "prediction_band": ("greybox._estimate.prediction", "prediction_band"),
    "delta_method": ("greybox._estimate.prediction", "delta_method"),
    "propagate": ("greybox._estimate.prediction", "propagate"),
    "raw_draws": ("greybox._estimate.prediction", "raw_draws"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.band import Band as Band
    from greybox._estimate.posterior import Posterior as Posterior
    from greybox._estimate.prediction import delta_method as delta_method
    from greybox._estimate.prediction import prediction_band as prediction_band
    from greybox._estimate.prediction import propagate as propagate
    from greybox._estimate.prediction import raw_draws as raw_draws
