"""greybox: grey-box identification of physical device models from measured data.

The core is pure (no file I/O, printing, plotting or global JAX configuration). Enable
float64 in your program before fitting: ``jax.config.update("jax_enable_x64", True)``.

The core names are here; the rest sit in public subpackages: `greybox.stochastic` (Kalman
filters, stochastic devices, sample paths), `greybox.design` (experiment and waveform
design), `greybox.blackbox`, `greybox.blocks`, `greybox.io`, `greybox.plots`, `greybox.video`.
Modules and packages whose names start with ``_`` are private.

Names are imported on first use (module `__getattr__`), so `import greybox` and the command
line's ``--help`` do not pay for JAX.
"""

import importlib.metadata
from typing import TYPE_CHECKING

from greybox._lazy import lazy_names

_SUBPACKAGES = ("blackbox", "blocks", "design", "io", "plots", "stochastic", "video")
# public name -> (module, attribute)
_NAMES = {
    "BatchResult": ("greybox._estimate.batch", "BatchResult"),
    "Device": ("greybox._estimate.batch", "Device"),
    "batch_table": ("greybox._estimate.batch", "batch_table"),
    "device_from_spec": ("greybox._estimate.batch", "device_from_spec"),
    "fit_batch": ("greybox._estimate.batch", "fit_batch"),
    "DISPLACEMENT": ("greybox._model.channels", "DISPLACEMENT"),
    "LASER_POWER": ("greybox._model.channels", "LASER_POWER"),
    "Channel": ("greybox._model.channels", "Channel"),
    "CandidateScore": ("greybox._estimate.compare", "CandidateScore"),
    "Experiment": ("greybox._model.data", "Experiment"),
    "AbstractDevice": ("greybox._model.device", "AbstractDevice"),
    "AbstractLinearDevice": ("greybox._model.device", "AbstractLinearDevice"),
    "AbstractODEDevice": ("greybox._model.device", "AbstractODEDevice"),
    "AbstractStateAffineDevice": ("greybox._model.device", "AbstractStateAffineDevice"),
    "AbstractSteppedDevice": ("greybox._model.device", "AbstractSteppedDevice"),
    "default_method": ("greybox._model.device", "default_method"),
    "with_camera": ("greybox._model.device", "with_camera"),
    "fit_distributed": ("greybox._estimate.distributed", "fit_distributed"),
    "InputError": ("greybox._model.errors", "InputError"),
    "FitResult": ("greybox._estimate.fit", "FitResult"),
    "ParameterEstimate": ("greybox._estimate.fit", "ParameterEstimate"),
    "ValidationResult": ("greybox._estimate.fit", "ValidationResult"),
    "fit": ("greybox._estimate.fit", "fit"),
    "validate": ("greybox._estimate.fit", "validate"),
    "FreeParameter": ("greybox._model.freeparams", "FreeParameter"),
    "IdentifiabilityReport": ("greybox._estimate.identifiability", "IdentifiabilityReport"),
    "fit_percent": ("greybox._estimate.metrics", "fit_percent"),
    "ZOH": ("greybox._estimate.noise_models", "ZOH"),
    "Adaptive": ("greybox._estimate.noise_models", "Adaptive"),
    "ExtendedKalmanFilter": ("greybox._estimate.noise_models", "ExtendedKalmanFilter"),
    "Huber": ("greybox._estimate.noise_models", "Huber"),
    "L2": ("greybox._estimate.noise_models", "L2"),
    "InitialState": ("greybox._estimate.noise_models", "InitialState"),
    "KalmanFilter": ("greybox._estimate.noise_models", "KalmanFilter"),
    "OutputError": ("greybox._estimate.noise_models", "OutputError"),
    "ProcessNoise": ("greybox._estimate.noise_models", "ProcessNoise"),
    "StudentT": ("greybox._estimate.noise_models", "StudentT"),
    "fit_percent_per_output": ("greybox._estimate.metrics", "fit_percent_per_output"),
    "mae": ("greybox._estimate.metrics", "mae"),
    "r_squared": ("greybox._estimate.metrics", "r_squared"),
    "rmse": ("greybox._estimate.metrics", "rmse"),
    "sae": ("greybox._estimate.metrics", "sae"),
    "ParameterInfo": ("greybox._model.parameters", "ParameterInfo"),
    "check_scalar_path": ("greybox._model.parameters", "check_scalar_path"),
    "get_value": ("greybox._model.parameters", "get_value"),
    "set_values": ("greybox._model.parameters", "set_values"),
    "with_overrides": ("greybox._model.parameters", "with_overrides"),
    "response_function": ("greybox._simulate.periodic", "response_function"),
    "response_surface": ("greybox._simulate.periodic", "response_surface"),
    "square_wave_cycle": ("greybox._simulate.periodic", "square_wave_cycle"),
    "square_wave_response": ("greybox._simulate.periodic", "square_wave_response"),
    "steady_state": ("greybox._simulate.periodic", "steady_state"),
    "PopulationFit": ("greybox._estimate.population", "PopulationFit"),
    "PopulationParameter": ("greybox._estimate.population", "PopulationParameter"),
    "population_fit": ("greybox._estimate.population", "population_fit"),
    "population_from_batch": ("greybox._estimate.population", "population_from_batch"),
    "Posterior": ("greybox._estimate.posterior", "Posterior"),
    "Band": ("greybox._estimate.prediction", "Band"),
    "delta_method": ("greybox._estimate.prediction", "delta_method"),
    "prediction_band": ("greybox._estimate.prediction", "prediction_band"),
    "propagate": ("greybox._estimate.prediction", "propagate"),
    "raw_draws": ("greybox._estimate.prediction", "raw_draws"),
    "with_shared": ("greybox._estimate.prediction", "with_shared"),
    "RunDiagnostics": ("greybox._estimate.likelihood", "RunDiagnostics"),
    "available_devices": ("greybox._registry", "available"),
    "device_module": ("greybox._registry", "device_module"),
    "get_device": ("greybox._registry", "get_device"),
    "parameter_table": ("greybox.report._markdown", "parameter_table"),
    "NoiseStructure": ("greybox.stochastic._sde_device", "NoiseStructure"),
    "as_arrays": ("greybox._simulate.simulate", "as_arrays"),
    "simulate": ("greybox._simulate.simulate", "simulate"),
    "DeviceSpec": ("greybox._model.spec", "DeviceSpec"),
    "DeviceSpecError": ("greybox._model.spec", "DeviceSpecError"),
    "Option": ("greybox._model.spec", "Option"),
    "LjungBox": ("greybox._estimate.stochastic_fit", "LjungBox"),
    "ljung_box": ("greybox._estimate.stochastic_fit", "ljung_box"),
    "CameraDefects": ("greybox._simulate.synthetic", "CameraDefects"),
    "record": ("greybox._simulate.synthetic", "record"),
    "TableFitResult": ("greybox._estimate.table_fit", "TableFitResult"),
    "fit_table": ("greybox._estimate.table_fit", "fit_table"),
    "PiecewiseConstant": ("greybox._model.waveforms", "PiecewiseConstant"),
    "PulseTrain": ("greybox._model.waveforms", "PulseTrain"),
    "concatenate": ("greybox._model.waveforms", "concatenate"),
    "from_samples": ("greybox._model.waveforms", "from_samples"),
    "multilevel_prbs": ("greybox._model.waveforms", "multilevel_prbs"),
    "stack_channels": ("greybox._model.waveforms", "stack_channels"),
}
__all__ = sorted(_NAMES) + list(_SUBPACKAGES)
__version__ = importlib.metadata.version("greybox")


__getattr__, __dir__ = lazy_names(__name__, _NAMES, _SUBPACKAGES)

if TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.batch import BatchResult as BatchResult
    from greybox._estimate.batch import Device as Device
    from greybox._estimate.batch import batch_table as batch_table
    from greybox._estimate.batch import device_from_spec as device_from_spec
    from greybox._estimate.batch import fit_batch as fit_batch
    from greybox._model.channels import DISPLACEMENT as DISPLACEMENT
    from greybox._model.channels import LASER_POWER as LASER_POWER
    from greybox._model.channels import Channel as Channel
    from greybox._estimate.compare import CandidateScore as CandidateScore
    from greybox._model.data import Experiment as Experiment
    from greybox._model.device import AbstractDevice as AbstractDevice
    from greybox._model.device import AbstractLinearDevice as AbstractLinearDevice
    from greybox._model.device import AbstractODEDevice as AbstractODEDevice
    from greybox._model.device import AbstractStateAffineDevice as AbstractStateAffineDevice
    from greybox._model.device import AbstractSteppedDevice as AbstractSteppedDevice
    from greybox._model.device import default_method as default_method
    from greybox._model.device import with_camera as with_camera
    from greybox._estimate.distributed import fit_distributed as fit_distributed
    from greybox._model.errors import InputError as InputError
    from greybox._estimate.fit import FitResult as FitResult
    from greybox._estimate.fit import ParameterEstimate as ParameterEstimate
    from greybox._estimate.fit import ValidationResult as ValidationResult
    from greybox._estimate.fit import fit as fit
    from greybox._estimate.fit import validate as validate
    from greybox._model.freeparams import FreeParameter as FreeParameter
    from greybox._estimate.identifiability import IdentifiabilityReport as IdentifiabilityReport
    from greybox._estimate.metrics import fit_percent as fit_percent
    from greybox._estimate.noise_models import ZOH as ZOH
    from greybox._estimate.noise_models import Adaptive as Adaptive
    from greybox._estimate.noise_models import ExtendedKalmanFilter as ExtendedKalmanFilter
    from greybox._estimate.noise_models import Huber as Huber
    from greybox._estimate.noise_models import L2 as L2
    from greybox._estimate.noise_models import InitialState as InitialState
    from greybox._estimate.noise_models import KalmanFilter as KalmanFilter
    from greybox._estimate.noise_models import OutputError as OutputError
    from greybox._estimate.noise_models import ProcessNoise as ProcessNoise
    from greybox._estimate.noise_models import StudentT as StudentT
    from greybox._estimate.metrics import fit_percent_per_output as fit_percent_per_output
    from greybox._estimate.metrics import mae as mae
    from greybox._estimate.metrics import r_squared as r_squared
    from greybox._estimate.metrics import rmse as rmse
    from greybox._estimate.metrics import sae as sae
    from greybox._model.parameters import ParameterInfo as ParameterInfo
    from greybox._model.parameters import check_scalar_path as check_scalar_path
    from greybox._model.parameters import get_value as get_value
    from greybox._model.parameters import set_values as set_values
    from greybox._model.parameters import with_overrides as with_overrides
    from greybox._simulate.periodic import response_function as response_function
    from greybox._simulate.periodic import response_surface as response_surface
    from greybox._simulate.periodic import square_wave_cycle as square_wave_cycle
    from greybox._simulate.periodic import square_wave_response as square_wave_response
    from greybox._simulate.periodic import steady_state as steady_state
    from greybox._estimate.population import PopulationFit as PopulationFit
    from greybox._estimate.population import PopulationParameter as PopulationParameter
    from greybox._estimate.population import population_fit as population_fit
    from greybox._estimate.population import population_from_batch as population_from_batch
    from greybox._estimate.posterior import Posterior as Posterior
    from greybox._estimate.prediction import Band as Band
    from greybox._estimate.prediction import delta_method as delta_method
    from greybox._estimate.prediction import prediction_band as prediction_band
    from greybox._estimate.prediction import propagate as propagate
    from greybox._estimate.prediction import raw_draws as raw_draws
    from greybox._estimate.prediction import with_shared as with_shared
    from greybox._estimate.likelihood import RunDiagnostics as RunDiagnostics
    from greybox._registry import available as available_devices
    from greybox._registry import device_module as device_module
    from greybox._registry import get_device as get_device
    from greybox.report._markdown import parameter_table as parameter_table
    from greybox.stochastic._sde_device import NoiseStructure as NoiseStructure
    from greybox._simulate.simulate import as_arrays as as_arrays
    from greybox._simulate.simulate import simulate as simulate
    from greybox._model.spec import DeviceSpec as DeviceSpec
    from greybox._model.spec import DeviceSpecError as DeviceSpecError
    from greybox._model.spec import Option as Option
    from greybox._estimate.stochastic_fit import LjungBox as LjungBox
    from greybox._estimate.stochastic_fit import ljung_box as ljung_box
    from greybox._simulate.synthetic import CameraDefects as CameraDefects
    from greybox._simulate.synthetic import record as record
    from greybox._estimate.table_fit import TableFitResult as TableFitResult
    from greybox._estimate.table_fit import fit_table as fit_table
    from greybox._model.waveforms import PiecewiseConstant as PiecewiseConstant
    from greybox._model.waveforms import PulseTrain as PulseTrain
    from greybox._model.waveforms import concatenate as concatenate
    from greybox._model.waveforms import from_samples as from_samples
    from greybox._model.waveforms import multilevel_prbs as multilevel_prbs
    from greybox._model.waveforms import stack_channels as stack_channels
