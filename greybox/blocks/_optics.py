"""Absorptance of the heated surfaces (PHYSICS.md §3, incoherent slab)."""

from __future__ import annotations

import jax.numpy as jnp

# Optical constants (n, k) [published]: Si from Green 2008, Au from Johnson & Christy 1972.
OPTICAL_CONSTANTS = {
    ("Si", 800e-9): (3.675, 5.41e-3),
    ("Si", 532e-9): (4.151, 3.31e-2),
    ("Au", 800e-9): (0.154, 4.908),
    ("Au", 532e-9): (0.558, 2.204),
}


def surface_reflectance(n, k):
    """Normal-incidence reflectance of one air/material surface."""
    return ((n - 1.0) ** 2 + k**2) / ((n + 1.0) ** 2 + k**2)


def slab_absorptance(n, k, wavelength_m, thickness_m):
    """Absorptance A of an incoherent slab (multiple reflections summed, no interference).

    A = (1 - R)(1 - e^{-a d}) / (1 - R e^{-a d}), R = surface reflectance, a = 4 pi k / lambda.
    A thick slab (or a metal) tends to 1 - R.
    """
    r = surface_reflectance(n, k)
    attenuation = jnp.exp(-4.0 * jnp.pi * k / wavelength_m * thickness_m)
    return (1.0 - r) * (1.0 - attenuation) / (1.0 - r * attenuation)


def material_absorptance(material: str, wavelength_m: float, thickness_m: float = 1.0):
    """Absorptance of bare Si or Au at 800 or 532 nm from the tabulated constants."""
    key = (material, round(wavelength_m, 12))
    matches = [
        v
        for (m, lam), v in OPTICAL_CONSTANTS.items()
        if m == material and abs(lam - wavelength_m) < 1e-12
    ]
    if not matches:
        known = sorted({f"{m} @ {lam * 1e9:.0f} nm" for m, lam in OPTICAL_CONSTANTS})
        raise ValueError(f"material/wavelength: no optical constants for {key}; known: {known}")
    n, k = matches[0]
    return slab_absorptance(n, k, wavelength_m, thickness_m)
