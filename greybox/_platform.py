"""Which kind of processor the computation being traced will run on.

The algorithms that differ between a CPU and an accelerator (the ZOH interval scan, the QR
of each Levenberg-Marquardt step) read it here. It follows `jax.default_device`, so a
`with jax.default_device(jax.devices("cpu")[0])` block on a GPU machine gets the CPU's
choices (JAX keys its compiled functions on that setting, so the two never mix)."""

from __future__ import annotations

import jax


def compute_platform() -> str:
    """"cpu", "gpu", "tpu", ...: the platform of the default device in effect."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def on_accelerator() -> bool:
    return compute_platform() != "cpu"
