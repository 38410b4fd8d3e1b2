"""`greybox track`: microscope video or image stack -> run CSV of displacement per frame."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import sys
from pathlib import Path

import numpy as np

HELP = """\
Track a feature of the device by sub-pixel image registration against a reference frame
and write a run CSV for `greybox fit`.

Input: a video file (AVI/MKV/MP4/MOV..., read with ffmpeg; use a lossless codec such as
FFV1 or H.264 -qp 0: lossy compression destroys sub-pixel accuracy), a multi-page TIFF,
or a folder of PNG/TIFF images (natural sort order).

Units and conventions:
  --roi X,Y,W,H   feature region in px in the reference frame (X = column, Y = row of
                  the top-left corner, 0-based); only moving structure should be inside.
  displacement    px relative to the reference frame (the mean of the first
                  --ref-frames frames); positive = +axis direction in the image
                  (x: rightwards / increasing column, y: downwards / increasing row).
  --um-per-px S   scale in um per px (e.g. 0.645 for 6.45 um pixels at 10x). Without it
                  only the px columns are written (no um columns), never guessed.
  t_s             s from the first frame: --fps if given, else the container's
                  per-frame timestamps, else its frame rate; image stacks need --fps.

Columns, one shuttle feature:  t_s,y_px[,y_um],quality,reason,sigma_px[,sigma_um]
Columns, --roi2 (two features, e.g. the micro-robot):
  t_s,f1_x_px,f1_y_px,f2_x_px,f2_y_px[,x_um,y_um],heading_rad,quality,reason,sigma_px
  (x, y = midpoint of the two features relative to the reference midpoint; heading =
  rotation of the f1->f2 vector, rad, from +x towards +y.)
quality is in [0, 1] (1 = identical to the reference up to translation). Flagged frames
have reason = glare | low_contrast | blur | lost | low_correlation | outlier_jump and
NaN displacement (the fitter masks them). sigma_px is the estimated 1-sigma error of
the frame's displacement (px), from its noise level and the texture's gradients.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "track",
        help="microscope video -> displacement CSV (sub-pixel tracking)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("video", metavar="VIDEO", help="video file, multi-page TIFF or image folder")
    p.add_argument("--roi", required=True, metavar="X,Y,W,H", help="feature ROI, px")
    p.add_argument(
        "--roi2",
        metavar="X,Y,W,H",
        help="second feature ROI, px: two-feature pose tracking (x, y, heading)",
    )
    p.add_argument(
        "--axis",
        choices=("x", "y"),
        default="x",
        help="motion axis of the shuttle (default x); one-feature mode only",
    )
    p.add_argument("--um-per-px", type=float, metavar="S", help="scale, um per px (> 0)")
    p.add_argument(
        "--fps",
        type=float,
        metavar="F",
        help="frame rate, frames/s (> 0); overrides the container's timing",
    )
    p.add_argument(
        "--ref-frames",
        type=int,
        default=1,
        metavar="K",
        help="average the first K frames as the reference (device at rest); "
        "cuts the reference's noise by sqrt(K) (default 1)",
    )
    p.add_argument(
        "--search-px",
        type=int,
        default=16,
        metavar="M",
        help="largest displacement searched, px: from the reference position "
        "(one feature) or from the previous frame (two features); default 16",
    )
    p.add_argument("--out", metavar="CSV", help="output run CSV (default runs/<VIDEO stem>.csv)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out even if it is a file greybox did not write",
    )
    p.add_argument(
        "--allow-short",
        action="store_true",
        help="write the CSV even when fewer frames decode than the container declares "
        "(a truncated or damaged video; the shortfall is still reported)",
    )
    p.set_defaults(func=run)
    return p


def _parse_roi(text: str, field: str):
    from greybox._model.errors import InputError
    from greybox.video._tracking import Roi

    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(
            f"expected four integers X,Y,W,H in px, got {text!r}", field=field
        ) from None
    if w < 8 or h < 8 or x < 0 or y < 0:
        raise InputError(f"needs X, Y >= 0 and W, H >= 8 px, got {text!r}", field=field)
    return Roi(x, y, w, h)


def _positive(value, field: str):
    from greybox._model.errors import InputError

    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"must be a positive number, got {value}", field=field)


def _times(info, n: int, fps: float | None, video: str) -> np.ndarray:
    from greybox._model.errors import InputError

    if fps is not None:
        return np.arange(n) / fps
    if info.timestamps_s is not None and len(info.timestamps_s) == n:
        return info.timestamps_s
    if info.fps is not None:
        return np.arange(n) / info.fps
    what = "an image stack has" if info.kind == "stack" else "the container has"
    raise InputError(
        f"{what} no frame timing; give the frame rate with --fps", file=video, field="--fps"
    )


def _fmt(v: float, digits: int) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.{digits}f}"


def is_track_csv(first_line: str) -> bool:
    """Whether a CSV's header is one `greybox track` writes (an earlier result to replace)."""
    cols = first_line.split(",")
    return cols[:1] == ["t_s"] and {"quality", "reason", "sigma_px"} <= set(cols)


def run(args) -> int:
    from greybox._extras import require_extra
    from greybox._model.errors import InputError

    require_extra("video", what="greybox track")
    from greybox.io._atomic import atomic_output_file, check_output_file
    from greybox.io._video import frame_shortfall, iter_frames, prefetch, probe
    from greybox.video._tracking import (
        FeatureTracker,
        measure_sequence,
        pose_track,
        reference_frame,
        saturation_level_for,
        search_crop,
        shuttle_track,
    )

    # Cheap checks first, so bad options fail before any decoding.
    _positive(args.um_per_px, "--um-per-px")
    _positive(args.fps, "--fps")
    if args.ref_frames < 1:
        raise InputError(f"must be >= 1, got {args.ref_frames}", field="--ref-frames")
    if args.search_px < 1:
        raise InputError(f"must be >= 1, got {args.search_px}", field="--search-px")
    rois = [_parse_roi(args.roi, "--roi")]
    if args.roi2 is not None:
        rois.append(_parse_roi(args.roi2, "--roi2"))
    video = args.video
    out = Path(args.out) if args.out else Path("runs") / f"{Path(video).stem}.csv"
    if Path(video).exists() and out.resolve() == Path(video).resolve():
        raise InputError("is the input video; give another file", file=str(out), field="--out")
    check_output_file(out, ours=is_track_csv, force=args.force)

    info = probe(video)
    for roi, field in zip(rois, ("--roi", "--roi2")):
        if not roi.inside(info.shape):
            raise InputError(
                f"ROI {roi.x},{roi.y},{roi.w},{roi.h} is outside the "
                f"{info.shape[1]}x{info.shape[0]} px frame",
                file=video,
                field=field,
            )
    follow = len(rois) == 2
    if follow:  # each feature's window moves with it: decode whole frames
        crop, track_rois = None, rois
    else:  # the window is fixed: let ffmpeg crop to it (the speed of one-ROI tracking)
        crop, roi_in_crop = search_crop(rois[0], args.search_px, info.shape)
        track_rois = [roi_in_crop]
    # A reader thread decodes the next chunk while this one is tracked; closing it (also
    # on an error) stops the thread and ffmpeg.
    with contextlib.closing(prefetch(iter_frames(video, info, crop=crop))) as chunks:
        first = next(chunks, None)
        if first is None or len(first) < 2:
            n = 0 if first is None else len(first)
            raise InputError(f"has {n} frame(s); tracking needs at least two", file=video)
        if args.ref_frames > len(first):
            raise InputError(f"must be <= {len(first)} (frames available)", field="--ref-frames")
        ref = reference_frame(first, 0, args.ref_frames)
        try:
            trackers = [
                FeatureTracker(
                    ref,
                    roi,
                    search_px=args.search_px,
                    saturation_level=saturation_level_for(info.dtype),
                )
                for roi in track_rois
            ]
        except ValueError as err:
            raise InputError(f"ROI {args.roi}: {err}", file=video, field="--roi") from None
        meas = measure_sequence(trackers, itertools.chain([first], chunks), follow=follow)
    n = len(meas[0].rho)
    short = frame_shortfall(info, n)
    if short is not None and not args.allow_short:
        raise InputError(
            f"{short}; nothing was written. Re-export or re-copy the video, or pass "
            "--allow-short to track the frames that decode",
            file=video,
        )
    if short is not None:
        print(f"greybox track: warning: {short}", file=sys.stderr)
    t = _times(info, n, args.fps, video)
    s = args.um_per_px
    with atomic_output_file(out) as fh:
        if len(rois) == 1:
            tr = shuttle_track(meas[0], args.axis)
            # The run format names the tracked coordinate y whatever the image axis.
            fh.write(
                ",".join(
                    ["t_s", "y_px"]
                    + (["y_um"] if s else [])
                    + ["quality", "reason", "sigma_px"]
                    + (["sigma_um"] if s else [])
                )
                + "\n"
            )
            for k in range(n):
                row = [_fmt(t[k], 6), _fmt(tr.y_px[k], 4)]
                row += [_fmt(tr.y_px[k] * s, 5)] if s else []
                row += [_fmt(tr.quality[k], 4), tr.reason[k], _fmt(tr.sigma_px[k], 4)]
                row += [_fmt(tr.sigma_px[k] * s, 5)] if s else []
                fh.write(",".join(row) + "\n")
            reason, sigma = tr.reason, tr.sigma_px
        else:
            pt = pose_track(meas[0], meas[1], rois[0], rois[1])
            fh.write(
                ",".join(
                    ["t_s", "f1_x_px", "f1_y_px", "f2_x_px", "f2_y_px"]
                    + (["x_um", "y_um"] if s else [])
                    + ["heading_rad", "quality", "reason", "sigma_px"]
                )
                + "\n"
            )
            for k in range(n):
                row = [_fmt(t[k], 6)] + [_fmt(v, 4) for v in (*pt.f1[k], *pt.f2[k])]
                row += [_fmt(pt.x_px[k] * s, 5), _fmt(pt.y_px[k] * s, 5)] if s else []
                row += [
                    _fmt(pt.heading_rad[k], 6),
                    _fmt(pt.quality[k], 4),
                    pt.reason[k],
                    _fmt(pt.sigma_px[k], 4),
                ]
                fh.write(",".join(row) + "\n")
            reason, sigma = pt.reason, pt.sigma_px
    bad = reason != ""
    kinds = ", ".join(f"{r} {int(np.sum(reason == r))}" for r in sorted(set(reason[bad])))
    med = np.nanmedian(sigma) if np.any(~bad) else float("nan")
    print(
        f"wrote {out}: {n} frames, {int(bad.sum())} flagged{' (' + kinds + ')' if kinds else ''}"
        f", median sigma {med:.4f} px" + ("" if s else "; no --um-per-px: px columns only")
    )
    return 0
