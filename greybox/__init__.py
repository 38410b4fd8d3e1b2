"""greybox: grey-box identification of physical device models from measured data.

The core is pure (no file I/O, printing, plotting or global JAX configuration). Enable
float64 in your program before fitting: ``jax.config.update("jax_enable_x64", True)``, or
``greybox.io.configure_jax()``, which also keeps compiled programs on disk as the commands do.

The core names are here (`__all__`): devices and their specs, experiments and waveforms,
`simulate`, `fit`/`validate` and their results, and the noise, simulation and loss settings.
The rest sit in public subpackages by job: `greybox.metrics` (scores and residual tests),
`greybox.waveforms` (input signals, periodic responses, synthetic recordings),
`greybox.parameters` (reading and setting parameter values), `greybox.uncertainty`
(prediction bands, propagation), `greybox.population` (batches, distributed and population
fits), `greybox.devices` (installed devices and helpers), `greybox.stochastic` (Kalman filters,
stochastic devices, sample paths), `greybox.design` (experiment and waveform design),
`greybox.blackbox`, `greybox.blocks`, `greybox.io`, `greybox.plots`, `greybox.video`. Names
that used to be at the top level still resolve, with a DeprecationWarning naming their home.
Modules and packages whose names start with ``_`` are private.

Names are imported on first use (module `__getattr__`), so `import greybox` and the command
line's ``--help`` do not pay for JAX.
"""

import importlib.metadata as _metadata
from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

_SUBPACKAGES = (
    "blackbox",
    "blocks",
    "design",
    "devices",
    "io",
    "metrics",
    "parameters",
    "plots",
    "population",
    "stochastic",
    "uncertainty",
    "video",
    "waveforms",
)
# public name -> (module, attribute)
_NAMES = {
    "DeviceSpec": ("greybox._model.spec", "DeviceSpec"),
    "DeviceSpecError": ("greybox._model.spec", "DeviceSpecError"),
    "Option": ("greybox._model.spec", "Option"),
    "ParameterInfo": ("greybox._model.parameters", "ParameterInfo"),
    "Channel": ("greybox._model.channels", "Channel"),
    "FreeParameter": ("greybox._model.freeparams", "FreeParameter"),
    "AbstractDevice": ("greybox._model.device", "AbstractDevice"),
    "AbstractLinearDevice": ("greybox._model.device", "AbstractLinearDevice"),
    "AbstractODEDevice": ("greybox._model.device", "AbstractODEDevice"),
    "AbstractStateAffineDevice": ("greybox._model.device", "AbstractStateAffineDevice"),
    "AbstractSteppedDevice": ("greybox._model.device", "AbstractSteppedDevice"),
    "Experiment": ("greybox._model.data", "Experiment"),
    "PiecewiseConstant": ("greybox._model.waveforms", "PiecewiseConstant"),
    "PulseTrain": ("greybox._model.waveforms", "PulseTrain"),
    "available_devices": ("greybox._registry", "available"),
    "get_device": ("greybox._registry", "get_device"),
    "device_module": ("greybox._registry", "device_module"),
    "simulate": ("greybox._simulate.simulate", "simulate"),
    "fit": ("greybox._estimate.fit", "fit"),
    "validate": ("greybox._estimate.fit", "validate"),
    "fit_batch": ("greybox._estimate.batch", "fit_batch"),
    "fit_table": ("greybox._estimate.table_fit", "fit_table"),
    "FitResult": ("greybox._estimate.fit", "FitResult"),
    "ValidationResult": ("greybox._estimate.fit", "ValidationResult"),
    "TableFitResult": ("greybox._estimate.table_fit", "TableFitResult"),
    "ParameterEstimate": ("greybox._estimate.fit", "ParameterEstimate"),
    "Posterior": ("greybox._estimate.posterior", "Posterior"),
    "Band": ("greybox._estimate.band", "Band"),
    "OutputError": ("greybox._estimate.noise_models", "OutputError"),
    "ProcessNoise": ("greybox._estimate.noise_models", "ProcessNoise"),
    "NoiseStructure": ("greybox.stochastic._sde_device", "NoiseStructure"),
    "InitialState": ("greybox._estimate.noise_models", "InitialState"),
    "KalmanFilter": ("greybox._estimate.noise_models", "KalmanFilter"),
    "ExtendedKalmanFilter": ("greybox._estimate.noise_models", "ExtendedKalmanFilter"),
    "ZOH": ("greybox._estimate.noise_models", "ZOH"),
    "Adaptive": ("greybox._estimate.noise_models", "Adaptive"),
    "Stiff": ("greybox._estimate.noise_models", "Stiff"),
    "Huber": ("greybox._estimate.noise_models", "Huber"),
    "StudentT": ("greybox._estimate.noise_models", "StudentT"),
    "L2": ("greybox._estimate.noise_models", "L2"),
    "InputError": ("greybox._model.errors", "InputError"),
}
# name that left the top level -> its public subpackage (still resolves, with a DeprecationWarning)
_MOVED = {
    "BatchResult": "population",
    "CameraDefects": "waveforms",
    "CandidateScore": "metrics",
    "DISPLACEMENT": "devices",
    "Device": "population",
    "IdentifiabilityReport": "metrics",
    "LASER_POWER": "devices",
    "LjungBox": "metrics",
    "PopulationFit": "population",
    "PopulationParameter": "population",
    "RunDiagnostics": "metrics",
    "as_arrays": "parameters",
    "batch_table": "population",
    "check_scalar_path": "parameters",
    "concatenate": "waveforms",
    "default_method": "devices",
    "delta_method": "uncertainty",
    "device_from_spec": "population",
    "fit_distributed": "population",
    "fit_percent": "metrics",
    "fit_percent_per_output": "metrics",
    "from_samples": "waveforms",
    "get_value": "parameters",
    "ljung_box": "metrics",
    "mae": "metrics",
    "multilevel_prbs": "waveforms",
    "parameter_table": "parameters",
    "population_fit": "population",
    "population_from_batch": "population",
    "prediction_band": "uncertainty",
    "propagate": "uncertainty",
    "r_squared": "metrics",
    "raw_draws": "uncertainty",
    "record": "waveforms",
    "response_function": "waveforms",
    "response_surface": "waveforms",
    "rmse": "metrics",
    "sae": "metrics",
    "set_values": "parameters",
    "square_wave_cycle": "waveforms",
    "square_wave_response": "waveforms",
    "stack_channels": "waveforms",
    "steady_state": "waveforms",
    "with_camera": "devices",
    "with_overrides": "parameters",
    "with_shared": "parameters",
}
__all__ = list(_NAMES)
try:
    __version__ = _metadata.version("greybox")
except _metadata.PackageNotFoundError:  # a source tree on PYTHONPATH, not installed (a GPU box)
    __version__ = "0+source"

__getattr__, __dir__ = _lazy_names(__name__, _NAMES, _SUBPACKAGES, moved=_MOVED)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.band import Band as Band
    from greybox._estimate.batch import fit_batch as fit_batch
    from greybox._estimate.fit import FitResult as FitResult
    from greybox._estimate.fit import ParameterEstimate as ParameterEstimate
    from greybox._estimate.fit import ValidationResult as ValidationResult
    from greybox._estimate.fit import fit as fit
    from greybox._estimate.fit import validate as validate
    from greybox._estimate.noise_models import L2 as L2
    from greybox._estimate.noise_models import ZOH as ZOH
    from greybox._estimate.noise_models import Adaptive as Adaptive
    from greybox._estimate.noise_models import ExtendedKalmanFilter as ExtendedKalmanFilter
    from greybox._estimate.noise_models import Huber as Huber
    from greybox._estimate.noise_models import InitialState as InitialState
    from greybox._estimate.noise_models import KalmanFilter as KalmanFilter
    from greybox._estimate.noise_models import OutputError as OutputError
    from greybox._estimate.noise_models import ProcessNoise as ProcessNoise
    from greybox._estimate.noise_models import Stiff as Stiff
    from greybox._estimate.noise_models import StudentT as StudentT
    from greybox._estimate.posterior import Posterior as Posterior
    from greybox._estimate.table_fit import TableFitResult as TableFitResult
    from greybox._estimate.table_fit import fit_table as fit_table
    from greybox._model.channels import Channel as Channel
    from greybox._model.data import Experiment as Experiment
    from greybox._model.device import AbstractDevice as AbstractDevice
    from greybox._model.device import AbstractLinearDevice as AbstractLinearDevice
    from greybox._model.device import AbstractODEDevice as AbstractODEDevice
    from greybox._model.device import AbstractStateAffineDevice as AbstractStateAffineDevice
    from greybox._model.device import AbstractSteppedDevice as AbstractSteppedDevice
    from greybox._model.errors import InputError as InputError
    from greybox._model.freeparams import FreeParameter as FreeParameter
    from greybox._model.parameters import ParameterInfo as ParameterInfo
    from greybox._model.spec import DeviceSpec as DeviceSpec
    from greybox._model.spec import DeviceSpecError as DeviceSpecError
    from greybox._model.spec import Option as Option
    from greybox._model.waveforms import PiecewiseConstant as PiecewiseConstant
    from greybox._model.waveforms import PulseTrain as PulseTrain
    from greybox._registry import available as available_devices  # noqa: F401 (re-exported)
    from greybox._registry import device_module as device_module
    from greybox._registry import get_device as get_device
    from greybox._simulate.simulate import simulate as simulate
    from greybox.stochastic._sde_device import NoiseStructure as NoiseStructure
