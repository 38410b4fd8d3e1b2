"""Black-box linear baselines: ARX, ARMAX (PEM), OE, recursive ARX/ARMAX, validation and
conversions (the MATLAB System Identification Toolbox workflow of thesis chapters 3-4).

Pure numpy/JAX; no printing, file I/O or global JAX configuration. Enable float64 in your
script (`jax.config.update("jax_enable_x64", True)`) for PEM fits to full precision.
"""

from ._armax import ARMAX as ARMAX, fit_armax as fit_armax
from ._arx import ARX as ARX, OrderSearch as OrderSearch
from ._arx import arx_order_search as arx_order_search, fit_arx as fit_arx
from ._convert import ContinuousTF as ContinuousTF, DiscreteTF as DiscreteTF
from ._convert import c2d as c2d, d2c as d2c, dc_gain as dc_gain, poles as poles
from ._convert import to_control as to_control, transfer_function as transfer_function
from ._convert import zeros as zeros
from ._data import UniformData as UniformData, detrend as detrend
from ._oe import OE as OE, fit_oe as fit_oe
from ._poly import Polynomials as Polynomials
from ._recursive import RecursiveEstimate as RecursiveEstimate
from ._recursive import recursive_armax as recursive_armax, recursive_arx as recursive_arx
from ._resample import interpolate as interpolate, resample as resample
from ._validation import Comparison as Comparison, ResidualTest as ResidualTest
from ._validation import compare as compare, innovations as innovations
from ._validation import n_initial as n_initial, predict as predict
from ._validation import residual_test as residual_test, simulate as simulate
from ._validation import step_response as step_response
