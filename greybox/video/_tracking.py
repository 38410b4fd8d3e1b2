"""Sub-pixel feature tracking on image arrays: registration, per-frame quality, flagging.

Pure: numpy arrays in, numpy arrays out; no file I/O, no printing.

Algorithm (per feature, against a reference frame; the feature is a user ROI):

1. **Coarse, whole pixel** (batched over all frames of a chunk, `scipy.fft` real FFTs
   in single precision): phase correlation of the tapered, zero-mean reference template
   with a search window = ROI grown by ``search_px`` on each side. Gives the integer
   displacement, up to ±``search_px``, and a parabolic estimate (about 0.1 px) of the
   peak's sub-pixel position.
2. **Pre-shift** (batched, Fourier shift theorem: one phase ramp per frame): the patch at
   the integer displacement is moved back by the parabolic estimate, so the residual left
   for step 3 is tiny. Without it the fixed taper, which does not move with the feature,
   pulls each estimate by a few % of its sub-pixel part towards the nearest whole pixel
   (measured on tests/test_tracking.py's sequences: bias 0.010 px at 0.75 px phase, RMS
   0.024 px at 0.5 px; with it: bias <= 0.005 px, RMS <= 0.013 px at every phase).
3. **Fine, sub-pixel**: scikit-image's `phase_cross_correlation`, frame by frame
   (``space="fourier"``, ``upsample_factor=upsample``, ``normalization=None``): the
   Guizar-Sicairos et al. (2008) upsampled-DFT refinement of the plain
   cross-correlation, which is the least-squares estimator for white noise and more
   noise-robust than phase whitening. The published implementation is used rather than
   our own (the issue asks for it); we only hand it the patch spectra, computed in one
   batched FFT. Its small matrix products run on one BLAS thread (`_one_blas_thread`):
   multithreaded OpenBLAS on 150 x 64 matrices spends its time synchronising (measured
   1.4-2 ms -> 10-25 ms per frame on the shared 2-core machine), and the other core is
   decoding video (`greybox.io._video.prefetch`). Its error metric gives ``rho``.
   In short: scikit-image does the sub-pixel registration; `scipy.fft` the batched
   whole-pixel search and patch spectra; numpy the parabola and phase ramp of step 2
   (a coarse starting point, not the estimate); threadpoolctl the BLAS thread limit.
4. **Per-frame quality**: ``rho`` = zero-mean, tapered normalised cross-correlation at
   the sub-pixel peak (invariant to illumination gain/offset drift); ``sharpness`` =
   mid-band spectral energy / total energy, relative to the reference (defocus);
   ``saturation`` = fraction of ROI pixels at the saturation level (glare).
5. **Honest sigma**: the noise energy implied by the decorrelation, N ≈ (1 - rho)·S,
   propagated through the least-squares shift estimator,
   ``sigma² = 2 σ_n² Σ W² g² / (Σ W g²)²`` (g = template gradient along the axis,
   W = taper², σ_n² = per-pixel noise variance, factor 2 = noise in both images).
   It grows with noise, blur and partial occlusion, and is the Cramér-Rao-like standard
   deviation a fitter can use as a per-frame weight (checked against the true error in
   the tests).

Flagging thresholds (`Thresholds`, why each value), tested in this order (first wins):

- ``glare``: saturated fraction above the reference's by > 0.5 % (a burst that clips the
  sensor destroys the texture in the clipped region; a few hot pixels do not).
- ``low_contrast``: ROI standard deviation < 25 % of the reference's (lamp off, dropped
  frame): the gain drift we accept is slow and far smaller.
- ``blur``: sharpness < 0.5 x reference (defocus: half the mid-band energy gone). Motion
  blur within the exposure is *not* flagged unless this severe: its centroid is the
  exposure-averaged position, which is what the camera model (PHYSICS.md §10) predicts.
- ``lost``: the whole-pixel peak puts the feature outside the search window or image.
- ``low_correlation``: rho < 0.5, or decorrelation 1 - rho > 4x the run's median and
  > median + 0.02 (dust, occlusion, a wrong peak). Relative, because the normal 1 - rho
  is set by the noise level of the run; 4x is far outside its chi-square scatter.
- ``outlier_jump``: a value that sits on the same side of both its good neighbours by
  more than max(``jump_px``, 8 x MAD of the run's second differences) and more than 3x
  the neighbours' own half-difference: a spike, not a step (real steps are kept) and
  not aliased fast motion (which inflates the MAD).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable, Sequence

import numpy as np
from scipy import fft as sfft
from skimage.registration import phase_cross_correlation
from threadpoolctl import ThreadpoolController

REASONS = ("glare", "low_contrast", "blur", "lost", "low_correlation", "outlier_jump")


@dataclasses.dataclass(frozen=True)
class Roi:
    """Region of interest in px: columns x..x+w-1, rows y..y+h-1 (0-based, x = column)."""

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self):
        if self.w < 8 or self.h < 8:
            raise ValueError(f"ROI must be at least 8x8 px, got {self.w}x{self.h}")

    def inside(self, shape: Sequence[int]) -> bool:
        """Whether the ROI lies wholly inside an image of shape (H, W)."""
        return (
            self.x >= 0
            and self.y >= 0
            and self.x + self.w <= shape[1]
            and self.y + self.h <= shape[0]
        )


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Flagging thresholds; see the module docstring for why each value."""

    glare_fraction: float = 0.005
    min_contrast: float = 0.25
    min_sharpness: float = 0.5
    min_rho: float = 0.5
    decorrelation_factor: float = 4.0
    decorrelation_margin: float = 0.02
    jump_px: float = 1.0


@dataclasses.dataclass(frozen=True)
class Measurements:
    """Raw per-frame registration of one feature; every field is (N,).

    ``dx_px``/``dy_px``: feature displacement relative to the reference frame, px
    (+x = increasing column, +y = increasing row). ``rho``, ``sharpness``, ``contrast``
    (ROI std / reference std), ``saturation`` (fraction), ``sigma_x_px``/``sigma_y_px``
    (estimated 1-sigma error, px), ``lost`` (bool: out of the search window or image).
    """

    dx_px: np.ndarray
    dy_px: np.ndarray
    rho: np.ndarray
    sharpness: np.ndarray
    contrast: np.ndarray
    saturation: np.ndarray
    sigma_x_px: np.ndarray
    sigma_y_px: np.ndarray
    lost: np.ndarray

    @staticmethod
    def concatenate(parts: Sequence[Measurements]) -> Measurements:
        """Join chunks along the frame axis."""
        return Measurements(
            **{
                f.name: np.concatenate([getattr(p, f.name) for p in parts])
                for f in dataclasses.fields(Measurements)
            }
        )


def _taper(n: int) -> np.ndarray:
    """1-D Tukey taper (cosine over the outer quarter each side): keeps most pixels while
    suppressing the wrap-around edge of the FFT correlation."""
    t = np.ones(n)
    m = max(1, n // 4)
    ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(m) + 0.5) / m))
    t[:m] = ramp
    t[n - m :] = ramp[::-1]
    return t


def _search_window(roi: Roi, search_px: int, shape, offset=(0, 0)):
    """Rows y0:y1, columns x0:x1 of the search window: the ROI at the expected position
    (shifted by ``offset`` (dx, dy) px) grown by ``search_px``, clipped to ``shape`` (H, W)."""
    ox, oy = offset
    return (
        max(roi.y + oy - search_px, 0),
        min(roi.y + oy + roi.h + search_px, shape[0]),
        max(roi.x + ox - search_px, 0),
        min(roi.x + ox + roi.w + search_px, shape[1]),
    )


def search_crop(
    roi: Roi, search_px: int, shape: Sequence[int]
) -> tuple[tuple[int, int, int, int], Roi]:
    """The only part of (H, W) frames a fixed-window `FeatureTracker` reads.

    Returns ``(crop, roi_in_crop)``: ``crop = (x, y, w, h)`` px, the search window at the
    reference position, and the ROI in the cropped frames' coordinates. A tracker built
    on cropped frames (reference included) gives the same displacements as on full ones,
    so a decoder can crop before the frames reach Python (`greybox.io._video.iter_frames`).
    """
    y0, y1, x0, x1 = _search_window(roi, int(search_px), shape)
    return (x0, y0, x1 - x0, y1 - y0), Roi(roi.x - x0, roi.y - y0, roi.w, roi.h)


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """The process's thread pools, inspected once (~0.3 ms; a limit from it costs ~3 us)."""
    return ThreadpoolController()


def _one_blas_thread():
    """Context manager: one BLAS thread for scikit-image's small matrix products (see the
    module docstring, step 3)."""
    return _blas_controller().limit(limits=1, user_api="blas")


class FeatureTracker:
    """Sub-pixel translation tracker for one ROI against a reference frame.

    **Arguments:**

    - ``reference``: (H, W) reference frame (any real dtype).
    - ``roi``: the feature in the reference frame; must lie inside it.
    - ``search_px``: largest displacement (px) from the expected position found by the
      whole-pixel search.
    - ``upsample``: sub-pixel refinement factor (1/upsample px resolution).
    - ``saturation_level``: grey level counted as saturated (e.g. 255 for uint8, see
      `saturation_level_for`); None = the reference dtype's maximum for integer
      references, no glare test for float ones (e.g. a `reference_frame` mean).
    """

    def __init__(
        self,
        reference: np.ndarray,
        roi: Roi,
        *,
        search_px: int = 16,
        upsample: int = 100,
        saturation_level: float | None = None,
    ):
        reference = np.asarray(reference)
        if reference.ndim != 2:
            raise ValueError(f"reference must be a 2-D frame, got shape {reference.shape}")
        if not roi.inside(reference.shape):
            raise ValueError(
                f"ROI {roi} is outside the {reference.shape[1]}x{reference.shape[0]} px frame"
            )
        if saturation_level is None and np.issubdtype(reference.dtype, np.integer):
            saturation_level = float(np.iinfo(reference.dtype).max)
        self.roi, self.search_px, self.upsample = roi, int(search_px), int(upsample)
        self.frame_shape = reference.shape
        self.saturation_level = saturation_level
        self._win = np.outer(_taper(roi.h), _taper(roi.w))
        tmpl = reference[roi.y : roi.y + roi.h, roi.x : roi.x + roi.w].astype(float)
        self._tmpl_std = float(tmpl.std())
        if self._tmpl_std == 0.0:
            raise ValueError(f"ROI {roi} has no contrast in the reference frame (flat)")
        tz = (tmpl - tmpl.mean()) * self._win
        self._tmpl_fft = np.fft.fft2(tz)
        fy = np.fft.fftfreq(roi.h)[:, None]
        fx = np.fft.fftfreq(roi.w)[None, :]
        self._fy = fy
        self._rfx = np.fft.rfftfreq(roi.w)[None, :]  # half-spectrum columns
        f = np.hypot(fx, fy)
        # Mid band, where texture beats shot noise and defocus removes energy.
        self._band = (f > 0.04) & (f < 0.2)
        self._sharp_ref = self._sharpness(self._tmpl_fft[None])[0]
        self._ref_sat = self._saturation(tmpl[None])[0]
        # Least-squares sigma factors per axis: sqrt(2 Σ W² g²) / Σ W g² (per unit σ_n).
        gy, gx = np.gradient(tmpl)
        w2 = self._win**2
        self._sig_gain = [np.sqrt(2.0 * np.sum(w2**2 * g**2)) / np.sum(w2 * g**2) for g in (gx, gy)]
        self._tz_energy = float(np.sum(tz**2))
        self._w2_sum = float(np.sum(w2))

    @staticmethod
    def _parabola(cc, py, px, axis):
        """Vertex offset (px, within ±0.5) of a parabola through the peak of cc (n, hs, ws)
        and its two neighbours along ``axis`` (0 = rows), with wrap-around."""
        n, hs, ws = cc.shape
        k = np.arange(n)
        if axis == 0:
            c0, cm, cp = cc[k, py, px], cc[k, (py - 1) % hs, px], cc[k, (py + 1) % hs, px]
        else:
            c0, cm, cp = cc[k, py, px], cc[k, py, (px - 1) % ws], cc[k, py, (px + 1) % ws]
        den = cm - 2.0 * c0 + cp
        off = np.where(den < 0, 0.5 * (cm - cp) / np.where(den < 0, den, -1.0), 0.0)
        return np.clip(off, -0.5, 0.5)

    def _sharpness(self, spec):
        power = np.abs(spec) ** 2
        return power[:, self._band].sum(axis=1) / np.maximum(power.sum(axis=(1, 2)), 1e-300)

    def _saturation(self, patches):
        if self.saturation_level is None:
            return np.zeros(len(patches))
        return np.mean(patches >= self.saturation_level, axis=(1, 2))

    def measure(self, frames: np.ndarray, offset: tuple[int, int] = (0, 0)) -> Measurements:
        """Register a batch of frames (n, H, W) whose feature is expected near ``offset``
        (dx, dy) px from its reference position; returns `Measurements` (n,)."""
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[1:] != self.frame_shape:
            raise ValueError(
                f"frames must be (n, {self.frame_shape[0]}, "
                f"{self.frame_shape[1]}), got {frames.shape}"
            )
        n = len(frames)
        r, m = self.roi, self.search_px
        H, W = self.frame_shape
        ox, oy = int(offset[0]), int(offset[1])
        y0, y1, x0, x1 = _search_window(r, m, (H, W), (ox, oy))
        nan = np.full(n, np.nan)
        lost_all = Measurements(nan, nan, nan, nan, nan, nan, nan, nan, np.ones(n, bool))
        if y1 - y0 < r.h or x1 - x0 < r.w:
            return lost_all
        win = frames[:, y0:y1, x0:x1].astype(np.float32)  # whole-pixel step only
        ty, tx = r.y - y0, r.x - x0  # template corner in the window at zero displacement
        # 1. whole-pixel phase correlation of the template (padded) against the window.
        # Real-input FFTs (half spectra) throughout, scipy's (faster than numpy's); this
        # whole-pixel step only needs the peak's position, so it runs in single precision
        # (2.6x faster again): s0 is refined in double precision below.
        hs, ws = win.shape[1:]
        canvas = np.zeros((hs, ws), np.float32)
        canvas[: r.h, : r.w] = np.fft.ifft2(self._tmpl_fft).real
        wz = win - win.mean(axis=(1, 2), keepdims=True)
        cross = sfft.rfft2(wz) * np.conj(sfft.rfft2(canvas))[None]
        cross /= np.maximum(np.abs(cross), np.float32(1e-12))
        cc = sfft.irfft2(cross, s=(hs, ws)).reshape(n, -1)
        py0, px0 = np.unravel_index(np.argmax(cc, axis=1), (hs, ws))
        # Patch corner in the window; corners past the last valid one are negative ones
        # wrapped around by the FFT (the feature left the window on that side).
        py = np.where(py0 > hs - r.h, py0 - hs, py0)
        px = np.where(px0 > ws - r.w, px0 - ws, px0)
        lost = (py < 0) | (px < 0)
        iy, ix = py - ty, px - tx  # whole-pixel displacement from the reference position
        py, px = np.clip(py, 0, hs - r.h), np.clip(px, 0, ws - r.w)
        rows = py[:, None] + np.arange(r.h)[None]
        cols = px[:, None] + np.arange(r.w)[None]
        # From the frames themselves (the float32 window is exact for 8/16-bit grey only).
        patches = frames[
            np.arange(n)[:, None, None], y0 + rows[:, :, None], x0 + cols[:, None, :]
        ].astype(float)
        # Parabolic sub-pixel estimate of the coarse peak (about 0.1 px): the patch is
        # moved back by it before the fine step, so the fixed taper's pull on the fine
        # residual (a few % of it) is negligible (module docstring, step 2).
        s0 = np.stack(
            [self._parabola(cc.reshape(n, hs, ws), py0, px0, ax) for ax in (0, 1)], 1
        ).astype(float)
        # 2. pre-shift by s0 (batched phase ramp), then 3. scikit-image, frame by frame.
        pz = patches - patches.mean(axis=(1, 2), keepdims=True)
        ramp = np.exp(2j * np.pi * s0[:, 0, None, None] * self._fy[None]) * np.exp(
            2j * np.pi * s0[:, 1, None, None] * self._rfx[None]
        )
        pz = sfft.irfft2(sfft.rfft2(pz) * ramp, s=(r.h, r.w))
        spec = sfft.fft2(pz * self._win[None])
        fine, err = np.empty((n, 2)), np.empty(n)
        with _one_blas_thread():
            for k in range(n):
                fine[k], err[k], _ = phase_cross_correlation(
                    self._tmpl_fft,
                    spec[k],
                    space="fourier",
                    upsample_factor=self.upsample,
                    normalization=None,
                )
        # `fine` registers the patch onto the template: the feature moved by minus that.
        dy = iy + s0[:, 0] - fine[:, 0]
        dx = ix + s0[:, 1] - fine[:, 1]
        rho = np.sqrt(np.clip(1.0 - err**2, 0.0, 1.0))
        # 4./5. quality and sigma.
        pstd = patches.std(axis=(1, 2))
        noise_var = (1.0 - rho) * self._tz_energy / self._w2_sum
        sig_n = np.sqrt(noise_var)
        return Measurements(
            dx_px=np.where(lost, np.nan, dx),
            dy_px=np.where(lost, np.nan, dy),
            rho=rho,
            sharpness=self._sharpness(spec) / self._sharp_ref,
            contrast=pstd / self._tmpl_std,
            saturation=self._saturation(patches) - self._ref_sat,
            sigma_x_px=sig_n * self._sig_gain[0],
            sigma_y_px=sig_n * self._sig_gain[1],
            lost=lost,
        )


def measure_sequence(
    trackers: Sequence[FeatureTracker], chunks: Iterable[np.ndarray], *, follow: bool = False
) -> list[Measurements]:
    """Run each tracker over the same frame chunks (each (n, H, W)), in one pass.

    ``follow=False``: the search window stays at the reference position (a shuttle that
    moves less than ``search_px``), batched per chunk. ``follow=True``: frame by frame,
    each search starts at the feature's last tracked position (a feature that travels
    far, e.g. on the micro-robot). Returns one `Measurements` per tracker.
    """
    parts = _measure_chunks(trackers, chunks, follow)
    if not parts or not parts[0]:
        raise ValueError("no frames to track")
    return [Measurements.concatenate(p) for p in parts]


def _measure_chunks(trackers, chunks, follow) -> list[list[Measurements]]:
    """The loop of `measure_sequence`: per tracker, the list of per-chunk (or per-frame)
    measurements."""
    parts = [[] for _ in trackers]
    last = [(0, 0) for _ in trackers]
    for chunk in chunks:
        for i, tracker in enumerate(trackers):
            if not follow:
                parts[i].append(tracker.measure(chunk))
                continue
            for frame in chunk:
                mk = tracker.measure(frame[None], offset=last[i])
                parts[i].append(mk)
                if not mk.lost[0]:
                    last[i] = (int(np.rint(mk.dx_px[0])), int(np.rint(mk.dy_px[0])))
    return parts


def _spikes(y: np.ndarray, good: np.ndarray, jump_px: float) -> np.ndarray:
    """Indices (bool mask) of isolated spikes among the good samples of y (see module doc)."""
    idx = np.flatnonzero(good)
    out = np.zeros(len(y), bool)
    if len(idx) < 3:
        return out
    v = y[idx]
    prev, mid, nxt = v[:-2], v[1:-1], v[2:]
    d2 = mid - 0.5 * (prev + nxt)
    mad = 1.4826 * np.median(np.abs(d2 - np.median(d2)))
    thr = max(jump_px, 8.0 * mad)
    same_side = np.sign(mid - prev) == np.sign(mid - nxt)
    spike = (
        same_side
        & (np.minimum(np.abs(mid - prev), np.abs(mid - nxt)) > thr)
        & (np.abs(d2) > 3.0 * 0.5 * np.abs(nxt - prev))
    )
    out[idx[1:-1][spike]] = True
    return out


def assess(
    meas: Measurements, signal_px: np.ndarray | None = None, thresholds: Thresholds = Thresholds()
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame quality in [0, 1] and flag reason ("" = good) for one feature.

    ``signal_px``: the tracked coordinate(s) used by the jump test, (N,) or (N, C);
    default: both ``dx_px`` and ``dy_px``. Returns ``(quality, reason)``, each (N,);
    quality = clip(rho, 0, 1) x clip(sharpness, 0, 1).
    """
    th = thresholds
    n = len(meas.rho)
    reason = np.full(n, "", dtype=object)

    def flag(mask, token):
        reason[(reason == "") & mask] = token

    with np.errstate(invalid="ignore"):
        flag(meas.saturation > th.glare_fraction, "glare")
        flag(meas.contrast < th.min_contrast, "low_contrast")
        flag(meas.sharpness < th.min_sharpness, "blur")
        flag(meas.lost, "lost")
        decor = 1.0 - meas.rho
        typical = np.nanmedian(decor[reason == ""]) if np.any(reason == "") else 0.0
        flag(
            (meas.rho < th.min_rho)
            | (
                (decor > th.decorrelation_factor * typical)
                & (decor > typical + th.decorrelation_margin)
            ),
            "low_correlation",
        )
        sig = (
            np.stack([meas.dx_px, meas.dy_px])
            if signal_px is None
            else np.atleast_2d(np.asarray(signal_px, dtype=float).T)
        )
        jump = np.zeros(n, bool)
        for s in sig:
            jump |= _spikes(s, reason == "", th.jump_px)
        flag(jump, "outlier_jump")
        quality = np.clip(np.nan_to_num(meas.rho), 0.0, 1.0) * np.clip(
            np.nan_to_num(meas.sharpness), 0.0, 1.0
        )
    return quality, reason.astype(str)


def _honest_sigma(sigma: np.ndarray, rho: np.ndarray, good: np.ndarray) -> np.ndarray:
    """NaN for flagged frames; frames that are (nearly) the reference itself get the
    median of the others: their decorrelation 1 - rho is ~0 (the reference frame when
    ``reference_count = 1``: ~1e-6 after the sub-pixel pre-shift, not exactly 0), so the
    noise estimate would be ~0 and the fitter's weight huge. A frame with its own noise
    decorrelates by about the run's median: < 1 % of it cannot happen by chance."""
    sigma = np.where(good, sigma, np.nan)
    decor = 1.0 - rho
    typical = np.nanmedian(decor[good]) if np.any(good) else 0.0
    exact = good & (decor <= 0.01 * typical)
    if np.any(good & ~exact):
        sigma[exact] = np.nanmedian(sigma[good & ~exact])
    return sigma


@dataclasses.dataclass(frozen=True)
class ShuttleTrack:
    """1-D track along ``axis``: ``y_px`` (N,) displacement, NaN where flagged;
    ``sigma_px``, ``quality``, ``reason`` (N,); ``meas`` the raw `Measurements`."""

    axis: str
    y_px: np.ndarray
    sigma_px: np.ndarray
    quality: np.ndarray
    reason: np.ndarray
    meas: Measurements


def shuttle_track(
    meas: Measurements, axis: str = "x", thresholds: Thresholds = Thresholds()
) -> ShuttleTrack:
    """Turn raw measurements into the 1-D shuttle track along ``axis`` ("x" or "y")."""
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x' or 'y', got {axis!r}")
    y = meas.dx_px if axis == "x" else meas.dy_px
    sig_axis = meas.sigma_x_px if axis == "x" else meas.sigma_y_px
    quality, reason = assess(meas, y, thresholds)
    good = reason == ""
    sigma = _honest_sigma(sig_axis, meas.rho, good)
    return ShuttleTrack(axis, np.where(good, y, np.nan), sigma, quality, reason, meas)


def reference_frame(frames: np.ndarray, start: int = 0, count: int = 1) -> np.ndarray:
    """Mean of ``count`` frames from ``start`` as the reference, (H, W) float.

    Averaging K frames of a device at rest (e.g. the pre-trigger baseline of a step
    response) cuts the reference's own noise by sqrt(K). That noise is a fixed-pattern
    error shared by every frame at a given displacement (about the per-frame sigma when
    K = 1), so it is the main remaining bias across sub-pixel phases.
    """
    frames = np.asarray(frames)
    if not 0 <= start < len(frames) or count < 1 or start + count > len(frames):
        raise ValueError(
            f"reference frames {start}..{start + count - 1} are outside the "
            f"{len(frames)}-frame sequence"
        )
    return frames[start : start + count].astype(float).mean(axis=0)


def saturation_level_for(dtype) -> float | None:
    """Grey level counted as saturated for frames of ``dtype`` (None for float data)."""
    dtype = np.dtype(dtype)
    return float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None


def track_shuttle(
    frames: np.ndarray,
    roi: Roi,
    *,
    axis: str = "x",
    reference: int = 0,
    reference_count: int = 1,
    search_px: int = 16,
    upsample: int = 100,
    chunk: int = 256,
    thresholds: Thresholds = Thresholds(),
) -> ShuttleTrack:
    """Track a shuttle feature in an in-memory stack ``frames`` (N, H, W) along ``axis``.

    Displacements in px relative to the mean of frames ``reference`` ..
    ``reference + reference_count - 1`` (`reference_frame`); see `FeatureTracker`.
    """
    frames = np.asarray(frames)
    tracker = FeatureTracker(
        reference_frame(frames, reference, reference_count),
        roi,
        search_px=search_px,
        upsample=upsample,
        saturation_level=saturation_level_for(frames.dtype),
    )
    (meas,) = measure_sequence(
        [tracker], (frames[i : i + chunk] for i in range(0, len(frames), chunk))
    )
    return shuttle_track(meas, axis, thresholds)


@dataclasses.dataclass(frozen=True)
class PoseTrack:
    """Two-feature (rigid body) track, all (N,) px or rad, NaN where flagged.

    ``f1``/``f2``: (N, 2) feature displacements (x, y) relative to the reference;
    ``x_px``/``y_px``: midpoint displacement; ``heading_rad``: rotation of the f1->f2
    vector relative to the reference (unwrapped, counter-clockwise in image axes, i.e.
    from +x towards +y); ``sigma_px``: larger feature sigma; ``quality``: the smaller.
    """

    f1: np.ndarray
    f2: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    heading_rad: np.ndarray
    sigma_px: np.ndarray
    quality: np.ndarray
    reason: np.ndarray


def pose_track(
    meas1: Measurements,
    meas2: Measurements,
    roi1: Roi,
    roi2: Roi,
    thresholds: Thresholds = Thresholds(),
) -> PoseTrack:
    """Combine two features' measurements into midpoint position and heading.

    A frame is flagged if either feature is (reason prefixed ``f1:``/``f2:``).
    """
    q1, r1 = assess(meas1, None, thresholds)
    q2, r2 = assess(meas2, None, thresholds)
    reason = np.where(
        r1 != "", np.char.add("f1:", r1), np.where(r2 != "", np.char.add("f2:", r2), "")
    )
    good = reason == ""
    f1 = np.column_stack([meas1.dx_px, meas1.dy_px])
    f2 = np.column_stack([meas2.dx_px, meas2.dy_px])
    c1 = np.array([roi1.x + roi1.w / 2.0, roi1.y + roi1.h / 2.0])
    c2 = np.array([roi2.x + roi2.w / 2.0, roi2.y + roi2.h / 2.0])
    v_ref = c2 - c1
    v = v_ref[None] + f2 - f1
    heading = np.arctan2(v[:, 1], v[:, 0]) - np.arctan2(v_ref[1], v_ref[0])
    heading = (heading + np.pi) % (2 * np.pi) - np.pi
    if np.any(good):  # unwrap over the good frames only (NaN would poison np.unwrap)
        heading[good] = np.unwrap(heading[good])
    mid = 0.5 * (f1 + f2)
    nanify = lambda a: np.where(good if a.ndim == 1 else good[:, None], a, np.nan)
    return PoseTrack(
        f1=nanify(f1),
        f2=nanify(f2),
        x_px=nanify(mid[:, 0]),
        y_px=nanify(mid[:, 1]),
        heading_rad=nanify(heading),
        sigma_px=np.fmax(
            *[
                _honest_sigma(np.fmax(m.sigma_x_px, m.sigma_y_px), m.rho, good)
                for m in (meas1, meas2)
            ]
        ),
        quality=np.minimum(q1, q2),
        reason=reason.astype(str),
    )


def track_pose(
    frames: np.ndarray,
    roi1: Roi,
    roi2: Roi,
    *,
    reference: int = 0,
    reference_count: int = 1,
    search_px: int = 16,
    upsample: int = 100,
    thresholds: Thresholds = Thresholds(),
) -> PoseTrack:
    """Track two features (each following its own last position) in ``frames`` (N, H, W)."""
    frames = np.asarray(frames)
    ref = reference_frame(frames, reference, reference_count)
    trackers = [
        FeatureTracker(
            ref,
            roi,
            search_px=search_px,
            upsample=upsample,
            saturation_level=saturation_level_for(frames.dtype),
        )
        for roi in (roi1, roi2)
    ]
    meas = measure_sequence(trackers, [frames], follow=True)
    return pose_track(meas[0], meas[1], roi1, roi2, thresholds)
