"""Black-box linear baselines: ARX, ARMAX (PEM), OE, recursive ARX/ARMAX, validation and
conversions (the MATLAB System Identification Toolbox workflow of thesis chapters 3-4).

Pure numpy/JAX; no printing, file I/O or global JAX configuration. Enable float64 in your
script (`jax.config.update("jax_enable_x64", True)`) for PEM fits to full precision.
"""

from ._armax import ARMAX as ARMAX
from ._armax import fit_armax as fit_armax
from ._arx import ARX as ARX
from ._arx import OrderSearch as OrderSearch
from ._arx import arx_order_search as arx_order_search
from ._arx import fit_arx as fit_arx
from ._convert import ContinuousTF as ContinuousTF
from ._convert import DiscreteTF as DiscreteTF
from ._convert import c2d as c2d
from ._convert import d2c as d2c
from ._convert import dc_gain as dc_gain
from ._convert import poles as poles
from ._convert import to_control as to_control
from ._convert import transfer_function as transfer_function
from ._convert import zeros as zeros
from ._data import UniformData as UniformData
from ._data import detrend as detrend
from ._oe import OE as OE
from ._oe import fit_oe as fit_oe
from ._poly import Polynomials as Polynomials
from ._recursive import RecursiveEstimate as RecursiveEstimate
from ._recursive import recursive_armax as recursive_armax
from ._recursive import recursive_arx as recursive_arx
from ._resample import interpolate as interpolate
from ._resample import resample as resample
from ._resample import uniform_from_experiment as uniform_from_experiment
from ._validation import Comparison as Comparison
from ._validation import ResidualTest as ResidualTest
from ._validation import compare as compare
from ._validation import innovations as innovations
from ._validation import n_initial as n_initial
from ._validation import predict as predict
from ._validation import residual_test as residual_test
from ._validation import simulate as simulate
from ._validation import step_response as step_response
