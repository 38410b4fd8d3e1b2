"""Helpers shared by the built-in device specs (written as any user's device file would be)."""

from __future__ import annotations

import dataclasses

import numpy as np


def rest_level_offsets(path: str, output: int = 0):
    """A `DeviceSpec.start_values` hook: start the per-run parameter at `path` (a camera offset)
    at the median rest reading of output `output` over the estimation runs.

    A camera reading is an image position (hundreds of um), so a per-run offset started at 0
    puts the fit far from the data. A run's rest reading is `Experiment.rest_level` (median
    before the input first switches on), or the median of all its frames with fewer than three
    frames before the onset.
    """

    def hook(model, free, experiments):
        del model
        if not experiments or not any(
            p.path == path and p.per_experiment and p.initial is None for p in free
        ):
            return tuple(free)
        rest = []
        for e in experiments:
            level = e.rest_level()[output]
            rest.append(level if np.isfinite(level) else np.nanmedian(e.y[:, output]))
        start = float(np.median(rest))
        return tuple(
            dataclasses.replace(p, initial=start)
            if p.path == path and p.per_experiment and p.initial is None
            else p
            for p in free
        )

    return hook
