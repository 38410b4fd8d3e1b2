"""Reading microscope videos and image stacks as grey frames; writing rendered sequences.

Library choice: imageio (image stacks, TIFF via tifffile) and imageio-ffmpeg (video). The
ffmpeg binary ships inside the imageio-ffmpeg wheel, so every container/codec ffmpeg knows
(AVI, MP4, MKV, MOV; FFV1, H.264, MJPEG, raw, ...) works on a fresh machine without a
system install or OpenCV. We call imageio-ffmpeg directly (rather than imageio's v3
wrapper) to ask ffmpeg for 8- or 16-bit *grey* frames, which decodes fast and keeps
16-bit camera data intact.

Timestamps: per-frame presentation times are read from the container (ffmpeg's
``framecrc`` muxer with ``-c copy``: packet pts without decoding; its Adler-32
checksum costs a fifth of ``framemd5``'s MD5 on uncompressed video). If they are missing or
do not match the decoded frame count, the container's frame rate is used
(t_k = k / fps); ``fps`` given by the caller overrides both. Image stacks have no time
base: they need ``fps``.

What the writers produce (`write_video`): ``.avi``/``.mkv`` = FFV1, lossless, 8- or
16-bit grey; ``.mp4`` = H.264 with ``-qp 0`` (lossless luma, 8-bit only). Lossy
compression (a default-quality MP4) destroys sub-pixel accuracy: never track those for
accuracy claims. `write_image_stack` writes one PNG (or TIFF) per frame.

Errors a user can cause raise `greybox._model.errors.InputError` naming the file.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import queue
import re
import subprocess
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np

from greybox._model.errors import InputError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
STACK_SUFFIXES = (".tif", ".tiff")  # a single file that can hold many pages


@dataclasses.dataclass(frozen=True)
class VideoInfo:
    """What a source is: ``kind`` ("video" or "stack"), ``shape`` (H, W), ``dtype``,
    ``fps`` (container frame rate or None), ``timestamps_s`` (container per-frame times
    relative to the first frame, or None), ``n_frames_expected`` (frames the container
    declares: its duration x frame rate, or None when it does not say)."""

    kind: str
    shape: tuple[int, int]
    dtype: np.dtype
    fps: float | None
    timestamps_s: np.ndarray | None
    n_frames_expected: int | None = None


def frame_shortfall(info: VideoInfo, n_decoded: int) -> str | None:
    """Why `n_decoded` frames are fewer than the container declares, or None if they are not.

    Compared with the container's duration x frame rate (a truncated file keeps its header)
    and with its packet count (frames present but not decodable)."""
    expected = info.n_frames_expected
    if expected is not None and n_decoded < expected - max(1, round(0.02 * expected)):
        return (
            f"decoded {n_decoded} frames but the container declares {expected} "
            "(duration x frame rate): the file looks truncated or damaged"
        )
    if info.timestamps_s is not None and n_decoded < len(info.timestamps_s) - 1:
        return (
            f"decoded {n_decoded} of the {len(info.timestamps_s)} frames the container "
            "holds: some frames could not be decoded"
        )
    return None


def _grey(img: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) image -> (H, W) grey, same dtype (luma weights for colour)."""
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] in (3, 4):
        y = img[..., :3].astype(float) @ np.array([0.299, 0.587, 0.114])
        return np.rint(y).astype(img.dtype) if np.issubdtype(img.dtype, np.integer) else y
    if img.ndim == 3 and img.shape[2] == 1:
        return img[..., 0]
    raise InputError(
        f"unsupported image shape {img.shape}; frames must be grey, RGB or RGBA images",
        field="VIDEO",
    )


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def _stack_files(path: Path) -> list[Path]:
    files = sorted(
        (p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key
    )
    if not files:
        raise InputError(
            f"folder holds no image files ({', '.join(IMAGE_SUFFIXES)})", file=str(path)
        )
    return files


def _ffmpeg_meta(path: Path) -> dict:
    """Container metadata from ffmpeg (fps, size, pix_fmt) without decoding frames."""
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray", bits_per_pixel=8)
    try:
        return next(gen)
    finally:
        gen.close()


def container_timestamps(path: str | os.PathLike) -> np.ndarray | None:
    """Per-frame presentation times (s, from 0) of the first video stream, or None.

    Reads packet pts with ffmpeg's framecrc muxer and ``-c copy`` (no decoding), sorted
    into presentation order.
    """
    cmd = [
        imageio_ffmpeg.get_ffmpeg_exe(),
        "-v",
        "error",
        "-i",
        str(path),
        "-map",
        "0:v:0",
        "-c",
        "copy",
        "-f",
        "framecrc",
        "-",
    ]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=120).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    tb = re.search(r"^#tb 0: (\d+)/(\d+)", out, re.M)
    pts = [
        int(line.split(",")[2])
        for line in out.splitlines()
        if line and not line.startswith("#") and line.split(",")[2].strip().lstrip("-").isdigit()
    ]
    if tb is None or len(pts) < 2:
        return None
    t = np.sort(np.array(pts, dtype=float)) * int(tb.group(1)) / int(tb.group(2))
    return t - t[0]


def probe(path: str | os.PathLike) -> VideoInfo:
    """Describe a video file, a multi-page TIFF or a folder of images (`VideoInfo`)."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", file=str(path))
    if path.is_dir():
        first = _grey(_read_image(_stack_files(path)[0]))
        return VideoInfo("stack", first.shape, first.dtype, None, None)
    if path.suffix.lower() in STACK_SUFFIXES:
        pages = _tiff_pages(path)
        return VideoInfo("stack", pages.shape[1:], pages.dtype, None, None)
    try:
        meta = _ffmpeg_meta(path)
    except (OSError, RuntimeError, StopIteration) as err:
        raise InputError(
            f"cannot be read as a video or image stack ({_first_line(err)})", file=str(path)
        ) from None
    w, h = meta["size"]
    deep = re.search(r"(gray|yuv\w*|rgb\w*|bgr\w*)(1[0-6])(le|be)", meta.get("pix_fmt", ""))
    dtype = np.dtype(np.uint16 if deep else np.uint8)
    fps = float(meta["fps"]) if meta.get("fps") and np.isfinite(meta["fps"]) else None
    fps = fps if fps and fps > 0 else None
    expected = None
    duration = meta.get("duration")
    nframes = meta.get("nframes")
    if isinstance(nframes, (int, float)) and np.isfinite(nframes) and nframes > 0:
        expected = int(nframes)
    elif fps and isinstance(duration, (int, float)) and np.isfinite(duration) and duration > 0:
        expected = int(round(duration * fps))
    return VideoInfo("video", (h, w), dtype, fps, container_timestamps(path), expected)


def _first_line(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return lines[-1] if lines else type(err).__name__


def _read_image(path: Path) -> np.ndarray:
    try:
        return np.asarray(iio.imread(path))
    except Exception:  # imageio raises many types (and plugin hints) for unreadable files
        raise InputError(
            "cannot be read as an image (not a valid PNG/TIFF/JPEG/BMP file)", file=str(path)
        ) from None


def iter_frames(
    path: str | os.PathLike,
    info: VideoInfo | None = None,
    *,
    chunk: int = 256,
    crop: tuple[int, int, int, int] | None = None,
) -> Iterator[np.ndarray]:
    """Yield grey frames in chunks, each (n <= chunk, H, W), of ``info.dtype``.

    Streaming keeps memory bounded for long videos; frames of a different size than the
    first raise `InputError`. ``crop = (x, y, w, h)`` px (x = column of the left edge,
    0-based; must lie inside the frame) yields only that region, (n, h, w): for a video
    ffmpeg crops inside the decoder process (after the grey conversion, so any offset is
    exact even for chroma-subsampled codecs), so full frames never cross the pipe; that
    is what makes tracking one ROI of a large frame fast (benchmarks/track.py).
    """
    path = Path(path)
    info = probe(path) if info is None else info
    if crop is not None:
        cx, cy, cw, ch = (int(v) for v in crop)
        if (
            cx < 0
            or cy < 0
            or cw < 1
            or ch < 1
            or cx + cw > info.shape[1]
            or cy + ch > info.shape[0]
        ):
            raise ValueError(
                f"crop {crop} (x, y, w, h px) is outside the "
                f"{info.shape[1]}x{info.shape[0]} px frame"
            )
    if info.kind == "video":
        deep = info.dtype == np.uint16
        pix = "gray16le" if deep else "gray"
        params = [] if crop is None else ["-vf", f"format={pix},crop={cw}:{ch}:{cx}:{cy}"]
        gen = imageio_ffmpeg.read_frames(
            str(path), pix_fmt=pix, output_params=params, bits_per_pixel=16 if deep else 8
        )
        h, w = info.shape if crop is None else (ch, cw)
        try:
            # imageio-ffmpeg warns that a cropped size differs from the source: intended.
            quiet = logging.getLogger("imageio_ffmpeg")
            level = quiet.level
            quiet.setLevel(logging.ERROR if crop is not None else level)
            try:
                next(gen)  # metadata
            finally:
                quiet.setLevel(level)
            buf = []
            for raw in gen:
                buf.append(np.frombuffer(raw, dtype="<u2" if deep else np.uint8).reshape(h, w))
                if len(buf) == chunk:
                    yield np.stack(buf).astype(info.dtype, copy=False)
                    buf = []
            if buf:
                yield np.stack(buf).astype(info.dtype, copy=False)
        except (OSError, RuntimeError) as err:
            raise InputError(
                f"video decoding failed ({_first_line(err)})", file=str(path)
            ) from None
        finally:
            gen.close()
        return
    if path.is_dir():
        files = _stack_files(path)
        for i in range(0, len(files), chunk):
            frames = [_grey(_read_image(f)) for f in files[i : i + chunk]]
            for f, fr in zip(files[i : i + chunk], frames):
                if fr.shape != info.shape:
                    raise InputError(
                        f"image is {fr.shape[1]}x{fr.shape[0]} px, the stack's "
                        f"first is {info.shape[1]}x{info.shape[0]}",
                        file=str(f),
                    )
            yield _crop(np.stack(frames), crop)
        return
    pages = _tiff_pages(path)
    for i in range(0, len(pages), chunk):
        yield _crop(pages[i : i + chunk], crop)


def _crop(frames: np.ndarray, crop) -> np.ndarray:
    if crop is None:
        return frames
    x, y, w, h = crop
    return np.ascontiguousarray(frames[:, y : y + h, x : x + w])


def prefetch(chunks: Iterable[np.ndarray], depth: int = 2) -> Iterator[np.ndarray]:
    """Yield the items of ``chunks`` while a background thread reads up to ``depth``
    ahead, so decoding (the ffmpeg process and the pipe reads, which release the GIL)
    overlaps the caller's work on the previous chunk (numpy FFTs and matrix products
    also release it). Without it ffmpeg stalls as soon as the pipe buffer (64 KiB, a few
    cropped frames) is full. An exception in the reader (e.g. `InputError` on a corrupt
    video) is re-raised here; closing this generator early stops and joins the reader.
    """
    items: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()
    end = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                items.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def reader():
        source = iter(chunks)
        try:
            for chunk in source:
                if not put((chunk, None)):
                    return
            put((end, None))
        except BaseException as err:  # handed to the consumer, re-raised there
            put((end, err))
        finally:
            close = getattr(source, "close", None)
            if close is not None:
                close()  # stops the ffmpeg process when the consumer quit early

    thread = threading.Thread(target=reader, name="greybox-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item, err = items.get()
            if item is end:
                if err is not None:
                    raise err
                return
            yield item
    finally:
        stop.set()
        thread.join()


def _tiff_pages(path: Path) -> np.ndarray:
    """A (multi-page) TIFF as (N, H, W) grey: a 2-D or RGB(A) file is one frame."""
    arr = _read_image(path)
    if arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] in (3, 4)):
        arr = arr[None]
    if arr.ndim == 4:
        arr = np.stack([_grey(p) for p in arr])
    if arr.ndim == 3:
        return arr
    raise InputError(f"unsupported TIFF layout {arr.shape}", file=str(path))


def read_frames(path: str | os.PathLike) -> tuple[np.ndarray, VideoInfo]:
    """Whole sequence in memory: ((N, H, W) frames, `VideoInfo`)."""
    info = probe(path)
    return np.concatenate(list(iter_frames(path, info))), info


def write_video(
    path: str | os.PathLike, frames: np.ndarray, fps: float, *, raw: bool = False
) -> Path:
    """Write grey ``frames`` (N, H, W) uint8/uint16 losslessly at ``fps`` frames/s.

    ``.avi``/``.mkv``: FFV1 (8- or 16-bit grey; ~6x smaller than raw, but decodes at only
    ~150 frames/s for 640x480 on one core); ``raw=True`` with ``.avi``: uncompressed grey
    (what scientific cameras record; decodes at >1000 frames/s); ``.mp4``: H.264
    ``-qp 0`` (8-bit only).
    """
    path = Path(path)
    frames = np.asarray(frames)
    suffix = path.suffix.lower()
    deep = frames.dtype == np.uint16
    if frames.dtype not in (np.uint8, np.uint16) or frames.ndim != 3:
        raise ValueError(
            f"frames must be (N, H, W) uint8 or uint16, got {frames.dtype} {frames.shape}"
        )
    if raw and suffix == ".avi":
        codec, params = "rawvideo", []
    elif suffix in (".avi", ".mkv"):
        codec, params = "ffv1", []
    elif suffix == ".mp4" and not deep:
        codec, params = "libx264", ["-qp", "0", "-preset", "ultrafast"]
    else:
        raise ValueError(
            f"cannot write {frames.dtype} frames losslessly to {suffix!r}; "
            "use .avi or .mkv (FFV1), or .mp4 for uint8"
        )
    pix = "gray16le" if deep else "gray"
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (frames.shape[2], frames.shape[1]),
        fps=fps,
        codec=codec,
        pix_fmt_in=pix,
        pix_fmt_out=pix,
        macro_block_size=1,
        quality=None,
        output_params=params,
        ffmpeg_log_level="error",
    )
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame.astype("<u2") if deep else frame))
    writer.close()
    return path


def write_image_stack(
    folder: str | os.PathLike, frames: np.ndarray, suffix: str = ".png"
) -> list[Path]:
    """Write ``frames`` (N, H, W) as ``folder/frame_00000.png`` ... (or ``.tif``)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, frame in enumerate(np.asarray(frames)):
        p = folder / f"frame_{k:05d}{suffix}"
        iio.imwrite(p, frame)
        paths.append(p)
    return paths
