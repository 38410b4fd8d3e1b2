"""Input waveforms and synthetic recordings: piecewise-constant and pulse-train
inputs, PRBS, joining and stacking them, periodic (square-wave) steady states and response
functions, and `record` (a simulated run with camera defects, as a lab would measure it).

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "PiecewiseConstant": ("greybox._model.waveforms", "PiecewiseConstant"),
    "PulseTrain": ("greybox._model.waveforms", "PulseTrain"),
    "concatenate": ("greybox._model.waveforms", "concatenate"),
    "from_samples": ("greybox._model.waveforms", "from_samples"),
    "multilevel_prbs": ("greybox._model.waveforms", "multilevel_prbs"),
    "stack_channels": ("greybox._model.waveforms", "stack_channels"),
    "square_wave_cycle": ("greybox._simulate.periodic", "square_wave_cycle"),
    "square_wave_response": ("greybox._simulate.periodic", "square_wave_response"),
    "steady_state": ("greybox._simulate.periodic", "steady_state"),
    "response_function": ("greybox._simulate.periodic", "response_function"),
    "response_surface": ("greybox._simulate.periodic", "response_surface"),
    "record": ("greybox._simulate.synthetic", "record"),
    "CameraDefects": ("greybox._simulate.synthetic", "CameraDefects"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._model.waveforms import PiecewiseConstant as PiecewiseConstant
    from greybox._model.waveforms import PulseTrain as PulseTrain
    from greybox._model.waveforms import concatenate as concatenate
    from greybox._model.waveforms import from_samples as from_samples
    from greybox._model.waveforms import multilevel_prbs as multilevel_prbs
    from greybox._model.waveforms import stack_channels as stack_channels
    from greybox._simulate.periodic import response_function as response_function
    from greybox._simulate.periodic import response_surface as response_surface
    from greybox._simulate.periodic import square_wave_cycle as square_wave_cycle
    from greybox._simulate.periodic import square_wave_response as square_wave_response
    from greybox._simulate.periodic import steady_state as steady_state
    from greybox._simulate.synthetic import CameraDefects as CameraDefects
    from greybox._simulate.synthetic import record as record
