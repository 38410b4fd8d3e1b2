"""Stochastic grey-box models: continuous-discrete Kalman filters and smoothers for linear
Gaussian SDEs, any device wrapped with process and measurement noise (`stochastic_device`),
its filter, log-likelihood and sample paths.

Fit one with `greybox.fit(model, experiments, free, noise=greybox.ProcessNoise(...))`."""

from greybox.stochastic._kalman import FilterGrid as FilterGrid
from greybox.stochastic._kalman import FilterResult as FilterResult
from greybox.stochastic._kalman import LinearGaussianSDE as LinearGaussianSDE
from greybox.stochastic._kalman import SmootherResult as SmootherResult
from greybox.stochastic._kalman import discretise as discretise
from greybox.stochastic._kalman import free_run as free_run
from greybox.stochastic._kalman import kalman_filter as kalman_filter
from greybox.stochastic._kalman import log_likelihood as log_likelihood
from greybox.stochastic._kalman import rts_smoother as rts_smoother
from greybox.stochastic._kalman import with_output_random_walks as with_output_random_walks
from greybox.stochastic._sde_device import DeviceFilterResult as DeviceFilterResult
from greybox.stochastic._sde_device import StochasticDevice as StochasticDevice
from greybox.stochastic._sde_device import device_filter as device_filter
from greybox.stochastic._sde_device import device_log_likelihood as device_log_likelihood
from greybox.stochastic._sde_device import draw_paths as draw_paths
from greybox.stochastic._sde_device import noise_parameters as noise_parameters
from greybox.stochastic._sde_device import sample_paths as sample_paths
from greybox.stochastic._sde_device import stochastic_device as stochastic_device
