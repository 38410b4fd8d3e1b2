"""Reading and setting a device's parameters: values by dotted path, overrides,
a fit's shared raw values put back into the device, float-array leaves (no recompiles) and
markdown tables of estimates.

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "ParameterInfo": ("greybox._model.parameters", "ParameterInfo"),
    "FreeParameter": ("greybox._model.freeparams", "FreeParameter"),
    "get_value": ("greybox._model.parameters", "get_value"),
    "set_values": ("greybox._model.parameters", "set_values"),
    "with_overrides": ("greybox._model.parameters", "with_overrides"),
    "with_shared": ("greybox._estimate.prediction", "with_shared"),
    "check_scalar_path": ("greybox._model.parameters", "check_scalar_path"),
    "as_arrays": ("greybox._simulate.simulate", "as_arrays"),
    "parameter_table": ("greybox.report._markdown", "parameter_table"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.prediction import with_shared as with_shared
    from greybox._model.freeparams import FreeParameter as FreeParameter
    from greybox._model.parameters import ParameterInfo as ParameterInfo
    from greybox._model.parameters import check_scalar_path as check_scalar_path
    from greybox._model.parameters import get_value as get_value
    from greybox._model.parameters import set_values as set_values
    from greybox._model.parameters import with_overrides as with_overrides
    from greybox._simulate.simulate import as_arrays as as_arrays
    from greybox.report._markdown import parameter_table as parameter_table
