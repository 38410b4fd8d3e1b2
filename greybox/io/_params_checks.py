"""Plausibility of a params.json beyond its schema: the numbers must agree with each other
and describe a camera that can exist (a hand-edited or damaged file is refused, located)."""

from __future__ import annotations

import math

from greybox._model.errors import InputError

MAX_EXPOSURE_S = 60.0  # no camera frame integrates light for longer than a minute
AGREE_RTOL = 1e-4  # raw and model.fitted spell one number (float32 transforms round)


def check_params_plausible(free, raw, fitted: dict, camera: dict, file: str) -> None:
    """`raw` (the fitted raw vector) and `model.fitted` name the same values; the camera's
    exposure is possible at its frame rate. Raises `InputError` naming the field."""
    exposure, fps = camera.get("exposure_s"), camera.get("fps")
    if exposure is not None:
        limit = MAX_EXPOSURE_S
        if isinstance(fps, (int, float)) and not isinstance(fps, bool) and fps > 0:
            limit = min(limit, 1.0 / fps * (1 + 1e-9))
        if not 0 <= exposure <= limit:
            raise InputError(
                f"{exposure:g} s is not a possible exposure (0 to {limit:g} s"
                + (f" at {fps:g} frames/s" if limit < MAX_EXPOSURE_S else "")
                + "); regenerate the file with `greybox fit`",
                file=file,
                field="model.camera.exposure_s",
            )
    shared = [p for p in free if not p.per_experiment]
    for p, r in zip(shared, raw):
        if p.path not in fitted:
            continue
        value = float(p.to_value(float(r)))
        given = float(fitted[p.path])
        if not math.isclose(value, given, rel_tol=AGREE_RTOL, abs_tol=1e-300):
            raise InputError(
                f"{p.path} is {given:.8g} but raw gives {value:.8g}: the two spellings of the "
                "fitted value disagree (an edited file?); regenerate it with `greybox fit`",
                file=file,
                field=f"model.fitted.{p.path}",
            )
