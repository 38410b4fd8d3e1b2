"""greybox: grey-box identification of physical device models from measured data.

The core is pure (no file I/O, printing, plotting or global JAX configuration). Enable
float64 in your program before fitting: ``jax.config.update("jax_enable_x64", True)``.

Everything public is importable from here (and from `greybox.blocks`, `greybox.blackbox`,
`greybox.io`, `greybox.video`); modules whose names start with ``_`` are private.
"""

import importlib.metadata

from greybox._batch import BatchResult as BatchResult
from greybox._batch import Device as Device
from greybox._batch import batch_table as batch_table
from greybox._batch import device_from_spec as device_from_spec
from greybox._batch import fit_batch as fit_batch
from greybox._channels import DISPLACEMENT as DISPLACEMENT
from greybox._channels import LASER_POWER as LASER_POWER
from greybox._channels import Channel as Channel
from greybox._compare import CandidateScore as CandidateScore
from greybox._data import Experiment as Experiment
from greybox._design import Design as Design
from greybox._design import DesignedRun as DesignedRun
from greybox._design import DesignProblem as DesignProblem
from greybox._design import LabConstraints as LabConstraints
from greybox._design import TrackingDesign as TrackingDesign
from greybox._design import comparison_table as comparison_table
from greybox._design import design_experiment as design_experiment
from greybox._design import design_problem as design_problem
from greybox._design import design_standard_errors as design_standard_errors
from greybox._design import det_gain as det_gain
from greybox._design import evaluate_design as evaluate_design
from greybox._design import format_design_table as format_design_table
from greybox._design import habitual_baseline as habitual_baseline
from greybox._design import run_information as run_information
from greybox._design import track_target as track_target
from greybox._device import AbstractDevice as AbstractDevice
from greybox._device import AbstractLinearDevice as AbstractLinearDevice
from greybox._device import AbstractODEDevice as AbstractODEDevice
from greybox._device import AbstractStateAffineDevice as AbstractStateAffineDevice
from greybox._device import AbstractSteppedDevice as AbstractSteppedDevice
from greybox._device import default_method as default_method
from greybox._device import with_camera as with_camera
from greybox._distributed import fit_distributed as fit_distributed
from greybox._errors import InputError as InputError
from greybox._fit import FitResult as FitResult
from greybox._fit import ParameterEstimate as ParameterEstimate
from greybox._fit import ValidationResult as ValidationResult
from greybox._fit import fit as fit
from greybox._fit import validate as validate
from greybox._freeparams import FreeParameter as FreeParameter
from greybox._identifiability import IdentifiabilityReport as IdentifiabilityReport
from greybox._kalman import FilterGrid as FilterGrid
from greybox._kalman import FilterResult as FilterResult
from greybox._kalman import LinearGaussianSDE as LinearGaussianSDE
from greybox._kalman import SmootherResult as SmootherResult
from greybox._kalman import discretise as discretise
from greybox._kalman import free_run as free_run
from greybox._kalman import kalman_filter as kalman_filter
from greybox._kalman import log_likelihood as log_likelihood
from greybox._kalman import rts_smoother as rts_smoother
from greybox._kalman import with_output_random_walks as with_output_random_walks
from greybox._metrics import fit_percent as fit_percent
from greybox._noise_models import L2 as L2
from greybox._noise_models import ZOH as ZOH
from greybox._noise_models import Adaptive as Adaptive
from greybox._noise_models import ExtendedKalmanFilter as ExtendedKalmanFilter
from greybox._noise_models import Huber as Huber
from greybox._noise_models import InitialState as InitialState
from greybox._noise_models import KalmanFilter as KalmanFilter
from greybox._noise_models import OutputError as OutputError
from greybox._noise_models import ProcessNoise as ProcessNoise
from greybox._noise_models import StudentT as StudentT
from greybox._metrics import fit_percent_per_output as fit_percent_per_output
from greybox._metrics import mae as mae
from greybox._metrics import r_squared as r_squared
from greybox._metrics import rmse as rmse
from greybox._metrics import sae as sae
from greybox._parameters import ParameterInfo as ParameterInfo
from greybox._parameters import check_scalar_path as check_scalar_path
from greybox._parameters import get_value as get_value
from greybox._parameters import set_values as set_values
from greybox._parameters import with_overrides as with_overrides
from greybox._periodic import response_function as response_function
from greybox._periodic import response_surface as response_surface
from greybox._periodic import square_wave_cycle as square_wave_cycle
from greybox._periodic import square_wave_response as square_wave_response
from greybox._periodic import steady_state as steady_state
from greybox._population import PopulationFit as PopulationFit
from greybox._population import PopulationParameter as PopulationParameter
from greybox._population import population_fit as population_fit
from greybox._population import population_from_batch as population_from_batch
from greybox._posterior import Posterior as Posterior
from greybox._prediction import Band as Band
from greybox._prediction import delta_method as delta_method
from greybox._prediction import prediction_band as prediction_band
from greybox._prediction import propagate as propagate
from greybox._prediction import raw_draws as raw_draws
from greybox._prediction import with_shared as with_shared
from greybox._likelihood import RunDiagnostics as RunDiagnostics
from greybox._registry import available as available_devices  # noqa: F401
from greybox._registry import device_module as device_module
from greybox._registry import get_device as get_device
from greybox._report import parameter_table as parameter_table
from greybox._sde_device import DeviceFilterResult as DeviceFilterResult
from greybox._sde_device import NoiseStructure as NoiseStructure
from greybox._sde_device import StochasticDevice as StochasticDevice
from greybox._sde_device import device_filter as device_filter
from greybox._sde_device import device_log_likelihood as device_log_likelihood
from greybox._sde_device import draw_paths as draw_paths
from greybox._sde_device import noise_parameters as noise_parameters
from greybox._sde_device import sample_paths as sample_paths
from greybox._sde_device import stochastic_device as stochastic_device
from greybox._simulate import as_arrays as as_arrays
from greybox._simulate import simulate as simulate
from greybox._spec import DeviceSpec as DeviceSpec
from greybox._spec import DeviceSpecError as DeviceSpecError
from greybox._spec import Option as Option
from greybox._stochastic import LjungBox as LjungBox
from greybox._stochastic import ljung_box as ljung_box
from greybox._synthetic import CameraDefects as CameraDefects
from greybox._synthetic import record as record
from greybox._table_fit import TableFitResult as TableFitResult
from greybox._table_fit import fit_table as fit_table
from greybox._waveforms import PiecewiseConstant as PiecewiseConstant
from greybox._waveforms import PulseTrain as PulseTrain
from greybox._waveforms import concatenate as concatenate
from greybox._waveforms import from_samples as from_samples
from greybox._waveforms import multilevel_prbs as multilevel_prbs
from greybox._waveforms import stack_channels as stack_channels
from greybox import plots as plots  # figures onto your own axes (matplotlib on first use)

__version__ = importlib.metadata.version("greybox")
