"""greybox: grey-box identification of laser-actuated thermal MEMS from camera data.

The core is pure (no file I/O, printing, plotting or global JAX configuration). Enable
float64 in your program before fitting: ``jax.config.update("jax_enable_x64", True)``.
"""

import importlib.metadata

from greybox.data import Experiment as Experiment
from greybox.device import AbstractDevice as AbstractDevice
from greybox.fit import FitResult as FitResult
from greybox.fit import ParameterEstimate as ParameterEstimate
from greybox.fit import ValidationResult as ValidationResult
from greybox.fit import fit as fit
from greybox.fit import validate as validate
from greybox.freeparams import FreeParameter as FreeParameter
from greybox.identifiability import IdentifiabilityReport as IdentifiabilityReport
from greybox.metrics import fit_percent as fit_percent
from greybox.metrics import rmse as rmse
from greybox.metrics import sae as sae
from greybox.parameters import ParameterInfo as ParameterInfo
from greybox.simulate import simulate as simulate
from greybox.waveforms import PiecewiseConstant as PiecewiseConstant
from greybox.waveforms import PulseTrain as PulseTrain
from greybox.waveforms import concatenate as concatenate
from greybox.waveforms import from_samples as from_samples
from greybox.waveforms import multilevel_prbs as multilevel_prbs
from greybox.waveforms import stack_channels as stack_channels

__version__ = importlib.metadata.version("greybox")
