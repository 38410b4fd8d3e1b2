"""Synthetic microscope image sequences with known sub-pixel motion (for tests and demos).

Pure numpy, deterministic for a given ``seed`` (one `numpy.random.Generator`), no file I/O
(`greybox.io._video` writes the frames to a video container or an image stack).

Model (PHYSICS.md §10): the scene is a sum of Gaussian blobs, convolved analytically with
a Gaussian PSF and the pixel box (variance 1/12 px²), so a frame at displacement ``d`` is
the scene translated by exactly ``d`` px: the truth is exact, with no interpolation.
Each frame averages ``M`` sub-exposure positions (motion blur over the exposure), so the
displacement an ideal tracker reports is the exposure average ``traj_px.mean(axis=1)``.
Then a slow illumination drift (gain and a left-right gradient), shot (Poisson) and read
noise, quantisation to 8 or 16 bits, and optional injected bad frames:

- ``"dust"``: an out-of-focus dark particle (opacity 0.85, radius 9 px) over the feature;
- ``"glare"``: a saturating bright burst (Gaussian, sigma 9 px) over the feature;
- ``"defocus"``: the whole frame blurred by a Gaussian of sigma 3.5 px;
- ``"dropout"``: the lamp or the frame lost: 3 % of the normal light.
"""

from __future__ import annotations

import dataclasses

import numpy as np

BAD_KINDS = ("dust", "glare", "defocus", "dropout")


@dataclasses.dataclass(frozen=True)
class RenderedSequence:
    """A rendered sequence and its truth.

    - ``frames``: (N, H, W) uint8 or uint16 grey levels.
    - ``truth_px``: exposure-averaged displacement per frame, (N,) for a shuttle (along
      the motion axis, relative to displacement 0) or (N, K, 2) (x, y) for K markers.
    - ``bad_kind``: (N,) str, ``""`` for good frames, else one of `BAD_KINDS`.
    """

    frames: np.ndarray
    truth_px: np.ndarray
    bad_kind: np.ndarray

    @property
    def bad(self) -> np.ndarray:
        """(N,) bool: frames with an injected defect."""
        return self.bad_kind != ""


def exposure_times(t_s, exposure_s: float, n_sub: int = 8) -> np.ndarray:
    """Times (N, n_sub) in s at which to sample a trajectory over each frame's exposure.

    Frame k is stamped at the END of its exposure (PHYSICS.md §10:
    p̄_k = mean of p over [t_k - T_e, t_k]); samples are midpoints of n_sub equal slices.
    Evaluate the model at these times, then pass the (N, n_sub) array in px to a renderer.
    """
    t = np.asarray(t_s, dtype=float)[:, None]
    frac = (np.arange(n_sub) + 0.5) / n_sub
    return t - exposure_s + exposure_s * frac[None, :]


def _gauss_1d(coord, centre, sigma):
    """exp(-(coord - centre)²/2σ²) for blobs (rows) x pixels (columns)."""
    return np.exp(-0.5 * ((coord[None, :] - centre[:, None]) / sigma[:, None]) ** 2)


def _blur_matrix(n: int, sigma: float) -> np.ndarray:
    """(n, n) row-normalised Gaussian blur operator (edges renormalised, no wrap-around)."""
    i = np.arange(n)
    k = np.exp(-0.5 * ((i[:, None] - i[None, :]) / sigma) ** 2)
    return k / k.sum(axis=1, keepdims=True)


def _disc(shape, centre_xy, radius, edge):
    """Soft-edged disc in [0, 1] (logistic edge of width ~edge px)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    r = np.hypot(xx - centre_xy[0], yy - centre_xy[1])
    return 1.0 / (1.0 + np.exp((r - radius) / edge))


def _finish(
    clean, *, rng, bad_kind, bad_center, full_well_e, read_noise_e, bit_depth, illumination_drift
):
    """Illumination drift, bad-frame injection, shot + read noise, quantisation.

    ``clean``: (N, H, W) intensity in [0, 1] (1 = full well). Returns integer frames.
    """
    n, h, w = clean.shape
    ramp = np.linspace(0.0, 1.0, n)[:, None, None]
    x = np.linspace(-0.5, 0.5, w)[None, None, :]
    # Slow lamp drift: global gain change plus a slowly growing left-right gradient.
    light = (1.0 - illumination_drift * ramp) * (1.0 + 0.5 * illumination_drift * ramp * x)
    img = clean * light
    cxy = (w / 2.0, h / 2.0) if bad_center is None else bad_center
    for k, kind in enumerate(bad_kind):
        if kind == "dust":
            img[k] *= 1.0 - 0.85 * _disc((h, w), cxy, 9.0, 1.5)
        elif kind == "glare":
            yy, xx = np.mgrid[0:h, 0:w]
            img[k] += 1.5 * np.exp(-((xx - cxy[0]) ** 2 + (yy - cxy[1]) ** 2) / (2 * 9.0**2))
        elif kind == "defocus":
            img[k] = _blur_matrix(h, 3.5) @ img[k] @ _blur_matrix(w, 3.5).T
        elif kind == "dropout":
            img[k] *= 0.03
        elif kind:
            raise ValueError(f"unknown bad-frame kind {kind!r}; expected one of {BAD_KINDS}")
    electrons = rng.poisson(np.clip(img, 0.0, None) * full_well_e).astype(float)
    electrons += rng.normal(0.0, read_noise_e, size=electrons.shape)
    top = 2**bit_depth - 1
    counts = np.clip(np.rint(electrons / full_well_e * top), 0, top)
    return counts.astype(np.uint8 if bit_depth == 8 else np.uint16)


def _bad_kinds(n, bad_frames):
    kinds = np.full(n, "", dtype=object)
    for k, kind in (bad_frames or {}).items():
        if kind not in BAD_KINDS:
            raise ValueError(f"unknown bad-frame kind {kind!r}; expected one of {BAD_KINDS}")
        kinds[k] = kind
    return kinds.astype(str)


def _as_exposure(traj, n_trailing):
    """(N,) or (N, M) (+ trailing dims) -> (N, M, ...) sub-exposure samples."""
    traj = np.asarray(traj, dtype=float)
    if traj.ndim == 1 + n_trailing:
        traj = traj[:, None]
    if traj.ndim != 2 + n_trailing or traj.shape[0] < 1:
        raise ValueError(
            f"trajectory must have shape (N,) or (N, M) per coordinate, got {traj.shape}"
        )
    return traj


def render_shuttle(
    traj_px,
    *,
    shape=(96, 128),
    axis: str = "x",
    seed: int = 0,
    psf_sigma_px: float = 1.0,
    blob_density: float = 0.03,
    full_well_e: float = 4000.0,
    read_noise_e: float = 8.0,
    bit_depth: int = 8,
    illumination_drift: float = 0.2,
    bad_frames: dict[int, str] | None = None,
    bad_center: tuple[float, float] | None = None,
) -> RenderedSequence:
    """Render a textured shuttle translating along ``axis`` by ``traj_px``.

    **Arguments:**

    - ``traj_px``: displacement in px, (N,) (instantaneous) or (N, M) (M samples over
      each frame's exposure, e.g. the model evaluated at `exposure_times`). Positive =
      towards increasing column (axis "x") or row (axis "y") index.
    - ``shape``: (H, W) frame size in px. The shuttle is a textured band across the middle
      60 % of the frame (perpendicular to ``axis``), on a fainter static substrate.
    - ``psf_sigma_px``: optical blur (Gaussian PSF sigma, px).
    - ``blob_density``: texture blobs per px² on the shuttle.
    - ``full_well_e``, ``read_noise_e``: electrons at intensity 1, read noise (electrons rms).
    - ``illumination_drift``: fractional lamp-gain loss over the run (with a gradient).
    - ``bad_frames``: {frame index: kind} with kind in `BAD_KINDS`; dust and glare are
      centred on ``bad_center`` (x, y) px (default: frame centre).

    **Returns:** `RenderedSequence` with ``truth_px`` = exposure mean of ``traj_px``, (N,).
    """
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x' or 'y', got {axis!r}")
    traj = _as_exposure(traj_px, 0)
    n = traj.shape[0]
    rng = np.random.default_rng(seed)
    h, w = shape if axis == "x" else shape[::-1]  # render along x, transpose for y
    bc = bad_center if (bad_center is None or axis == "x") else bad_center[::-1]
    reach = float(np.max(np.abs(traj))) + 6.0 * 3.0
    pad = 4.0 * 3.0 + reach

    def blobs(count, y_lo, y_hi, amp):
        xb = rng.uniform(-pad, w + pad, count)
        yb = rng.uniform(y_lo, y_hi, count)
        sb = rng.uniform(1.0, 2.5, count)
        ab = rng.choice([-1.0, 1.0], count) * rng.uniform(0.5, 1.0, count) * amp
        # Gaussian blob (*) Gaussian PSF (*) pixel box (variance 1/12 px²): still Gaussian.
        return xb, yb, np.sqrt(sb**2 + psf_sigma_px**2 + 1.0 / 12.0), ab

    y0, y1 = 0.2 * h, 0.8 * h
    rows = np.arange(h, dtype=float)
    cols = np.arange(w, dtype=float)
    edge = np.sqrt(psf_sigma_px**2 + 1.0 / 12.0)
    band = 1.0 / (1.0 + np.exp(-(rows - y0) / edge)) - 1.0 / (1.0 + np.exp(-(rows - y1) / edge))
    # Static substrate: faint texture; the shuttle: strong texture on a brighter level.
    xs, ys, ss, as_ = blobs(int(0.01 * h * (w + 2 * pad)), 0, h, 0.08)
    substrate = 0.30 + (_gauss_1d(rows, ys, ss).T * as_) @ _gauss_1d(cols, xs, ss)
    n_sh = int(blob_density * (y1 - y0) * (w + 2 * pad))
    xb, yb, sb, ab = blobs(n_sh, y0 + 2.0, y1 - 2.0, 0.22)
    gy = _gauss_1d(rows, yb, sb).T * ab  # (H, nb)
    clean = np.empty((n, h, w))
    for k in range(n):
        # Exposure average of the moving texture: average the x-profiles, then one matmul.
        gx = np.mean([_gauss_1d(cols, xb + d, sb) for d in traj[k]], axis=0)
        shuttle = 0.52 + gy @ gx
        clean[k] = substrate + band[:, None] * (shuttle - substrate)
    kinds = _bad_kinds(n, bad_frames)
    frames = _finish(
        clean,
        rng=rng,
        bad_kind=kinds,
        bad_center=bc,
        full_well_e=full_well_e,
        read_noise_e=read_noise_e,
        bit_depth=bit_depth,
        illumination_drift=illumination_drift,
    )
    if axis == "y":
        frames = np.ascontiguousarray(frames.transpose(0, 2, 1))
    return RenderedSequence(frames=frames, truth_px=traj.mean(axis=1), bad_kind=kinds)


def render_markers(
    points_px,
    *,
    shape=(120, 160),
    seed: int = 0,
    marker_sigma_px: float = 2.5,
    psf_sigma_px: float = 1.0,
    full_well_e: float = 4000.0,
    read_noise_e: float = 8.0,
    bit_depth: int = 8,
    illumination_drift: float = 0.1,
    bad_frames: dict[int, str] | None = None,
    bad_center: tuple[float, float] | None = None,
) -> RenderedSequence:
    """Render K bright round markers on a uniform body (e.g. two features on the micro-robot).

    ``points_px``: marker centres (x, y) in px, (N, K, 2) or (N, M, K, 2) with M samples
    over the exposure. Round markers keep translation-only tracking valid while the body
    rotates (a textured patch would decorrelate with heading). Other arguments as in
    `render_shuttle`. ``truth_px`` is the exposure mean, (N, K, 2).
    """
    pts = _as_exposure(points_px, 2)
    n = pts.shape[0]
    rng = np.random.default_rng(seed)
    h, w = shape
    rows = np.arange(h, dtype=float)
    cols = np.arange(w, dtype=float)
    s = np.sqrt(marker_sigma_px**2 + psf_sigma_px**2 + 1.0 / 12.0)
    # Untextured body around the markers: static texture inside a feature's ROI would
    # pull the estimate towards zero (a tracked ROI must hold only moving structure).
    background = np.full((h, w), 0.25)
    clean = np.empty((n, h, w))
    for k in range(n):
        sub = pts[k].reshape(-1, 2)  # all (sample, marker) centres
        sig = np.full(len(sub), s)
        gy = _gauss_1d(rows, sub[:, 1], sig).T
        gx = _gauss_1d(cols, sub[:, 0], sig)
        clean[k] = background + 0.5 * (gy @ gx) / pts.shape[1]
    kinds = _bad_kinds(n, bad_frames)
    frames = _finish(
        clean,
        rng=rng,
        bad_kind=kinds,
        bad_center=bad_center,
        full_well_e=full_well_e,
        read_noise_e=read_noise_e,
        bit_depth=bit_depth,
        illumination_drift=illumination_drift,
    )
    return RenderedSequence(frames=frames, truth_px=pts.mean(axis=1), bad_kind=kinds)
