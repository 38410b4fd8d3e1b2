"""Gaussian laser spot and the fraction of its power that lands on rectangular targets.

PHYSICS.md §3: for I(x, y) = 2P/(pi w^2) exp(-2 r^2 / w^2) (w = 1/e^2 radius), the power
fraction on [x1, x2] x [y1, y2] is the closed-form product of erf differences. A frame is an
outer rectangle minus its hole. All lengths in m.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax.scipy.special import erf


class GaussianSpot(eqx.Module):
    """TEM00 spot: 1/e^2 radius `waist_m` [m], centre (`x_m`, `y_m`) [m] in the target frame."""

    waist_m: float
    x_m: float = 0.0
    y_m: float = 0.0

    def __check_init__(self):
        if isinstance(self.waist_m, (int, float)) and not self.waist_m > 0:
            raise ValueError(f"waist_m: {self.waist_m} must be > 0 (1/e^2 spot radius in m)")

    def shifted_to_body(self, body_x_m, body_y_m, heading_rad) -> GaussianSpot:
        """This world-fixed spot expressed in the coordinates of a body at the given pose.

        Exact for heading 0; approximate while the rotation is small against the frame size.
        """
        c, s = jnp.cos(heading_rad), jnp.sin(heading_rad)
        dx, dy = self.x_m - body_x_m, self.y_m - body_y_m
        return GaussianSpot(self.waist_m, c * dx + s * dy, -s * dx + c * dy)


class Rectangle(eqx.Module):
    """Axis-aligned rectangle [x_min_m, x_max_m] x [y_min_m, y_max_m] (m)."""

    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float

    def __check_init__(self):
        for lo, hi, name in ((self.x_min_m, self.x_max_m, "x"), (self.y_min_m, self.y_max_m, "y")):
            if isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and not hi > lo:
                raise ValueError(f"{name}_max_m: must exceed {name}_min_m ({hi} <= {lo})")

    @staticmethod
    def centred(x_m: float, y_m: float, width_m: float, height_m: float) -> Rectangle:
        return Rectangle(
            x_m - width_m / 2, x_m + width_m / 2, y_m - height_m / 2, y_m + height_m / 2
        )

    def fraction(self, spot: GaussianSpot):
        """Fraction (0..1) of the spot's power falling on this rectangle (closed form)."""
        k = jnp.sqrt(2.0) / spot.waist_m
        fx = erf(k * (self.x_max_m - spot.x_m)) - erf(k * (self.x_min_m - spot.x_m))
        fy = erf(k * (self.y_max_m - spot.y_m)) - erf(k * (self.y_min_m - spot.y_m))
        return 0.25 * fx * fy


class RectangularFrame(eqx.Module):
    """Open frame = `outer` rectangle minus `hole` (None for a solid pad)."""

    outer: Rectangle
    hole: Rectangle | None = None

    @staticmethod
    def square(x_m: float, y_m: float, outer_m: float, hole_m: float = 0.0) -> RectangularFrame:
        hole = Rectangle.centred(x_m, y_m, hole_m, hole_m) if hole_m > 0 else None
        return RectangularFrame(Rectangle.centred(x_m, y_m, outer_m, outer_m), hole)

    def fraction(self, spot: GaussianSpot):
        inner = 0.0 if self.hole is None else self.hole.fraction(spot)
        return self.outer.fraction(spot) - inner
