"""Camera frames: decoding and encoding mp4 with PyAV (the ``video`` extra), PNG cells, resizing.

Decoding reads any codec FFmpeg reads, among them AV1 (LeRobot's default, libsvtav1) and H.264.
A dataset row asks for the frame at a timestamp (seconds from the file's start): the frame
nearest to it is taken, and a row with no frame within half a frame period (``0.5 / fps``) is one
error naming the file and the timestamp. Frames are resized as they are decoded (PIL, bilinear
with antialiasing), so memory holds only frames at the requested size.
"""

from __future__ import annotations

import io
from pathlib import Path
import numpy as np

PIX_FMT = "yuv420p"
CODEC = "h264"


def _av():
    try:
        import av
    except ImportError:
        raise ValueError("camera features: reading and writing camera video needs PyAV: "
                         "pip install \"action-decoder[video]\"") from None
    return av


def image_hw(image_size, field: str = "image_size") -> tuple[int, int] | None:
    """``(H, W)`` from an int (square) or a pair, None for None (native size)."""
    if image_size is None:
        return None
    pair = (image_size, image_size) if isinstance(image_size, (int, np.integer)) else \
        tuple(image_size) if isinstance(image_size, (tuple, list)) else ()
    if len(pair) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in pair):
        raise ValueError(f"{field}: expected a positive int or (height, width) of positive ints, got {image_size!r}")
    return int(pair[0]), int(pair[1])


def resize(image, size: tuple[int, int] | None) -> np.ndarray:
    """``image`` (a PIL image or uint8 ``[h, w, 3]``) as uint8 RGB ``[H, W, 3]`` at ``size`` (None: as it is)."""
    from PIL import Image

    image = image if isinstance(image, Image.Image) else Image.fromarray(np.asarray(image, np.uint8))
    image = image.convert("RGB")
    if size is not None and image.size != (size[1], size[0]):
        image = image.resize((size[1], size[0]), Image.BILINEAR, reducing_gap=None)
    return np.asarray(image, np.uint8)


def decode_png(cell, where: str, size: tuple[int, int] | None, root: Path | None = None) -> np.ndarray:
    """One ``dtype: image`` cell (LeRobot's struct ``{bytes, path}``, or raw bytes) as ``[H, W, 3]``."""
    from PIL import Image, UnidentifiedImageError

    data = cell.get("bytes") if isinstance(cell, dict) else cell
    try:
        if data:
            return resize(Image.open(io.BytesIO(data)), size)
        path = Path(cell["path"]) if isinstance(cell, dict) and cell.get("path") else None
        if path is not None and not path.is_absolute() and root is not None:
            path = root / path
        if path is None or not path.is_file():
            raise ValueError(f"{where}: expected image bytes or the path of an image file, got "
                             f"{None if path is None else str(path)!r} (no such file)")
        return resize(Image.open(path), size)
    except (UnidentifiedImageError, OSError) as err:
        raise ValueError(f"{where}: expected an encoded image (PNG/JPEG), got unreadable bytes ({err})") from None


def read_frames(path: Path, timestamps: np.ndarray, fps: float, size: tuple[int, int] | None) -> np.ndarray:
    """Frames ``[n, H, W, 3]`` uint8 of the video at ``path`` nearest to ``timestamps [n]`` (seconds
    from the file's start), decoded once in stream order."""
    av = _av()
    if not path.is_file():
        raise ValueError(f"{path}: expected the video file of this camera, the file is missing")
    times, frames = [], []
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ValueError(f"{path}: expected a video stream, found none")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                times.append(float(frame.pts * stream.time_base) if frame.pts is not None else len(times) / fps)
                frames.append(resize(frame.to_image(), size))                  # [H, W, 3]
    except av.error.FFmpegError as err:
        raise ValueError(f"{path}: expected a readable video, got a decoding error ({err})") from None
    if not frames:
        raise ValueError(f"{path}: expected video frames, decoded none")
    times = np.asarray(times)
    by_time = np.argsort(times, kind="stable")
    times = times[by_time]
    right = np.clip(np.searchsorted(times, timestamps), 1, len(times) - 1) if len(times) > 1 else np.zeros(
        len(timestamps), np.int64)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(times[left] - timestamps) <= np.abs(times[right] - timestamps), left, right)
    gap = np.abs(times[nearest] - timestamps)
    if (gap > 0.5 / fps).any():
        bad = int(np.argmax(gap > 0.5 / fps))
        raise ValueError(f"{path}: expected a frame within {0.5 / fps:.4g} s (half a frame at {fps:g} fps) of "
                         f"timestamp {timestamps[bad]:.4f} s, the nearest is at {times[nearest[bad]]:.4f} s (the file "
                         f"holds {len(times)} frames, {times[0]:.4f}-{times[-1]:.4f} s)")
    return np.stack([frames[by_time[i]] for i in nearest])


def write_video(path: Path, frames: np.ndarray, fps: float, codec: str = CODEC, crf: int = 18) -> dict:
    """Encode ``frames [T, H, W, 3]`` uint8 as an mp4 (``codec``, yuv420p, every frame at ``k / fps``
    s) and return LeRobot's ``info`` of the stream (``video.codec``, ``video.pix_fmt``, ...)."""
    av = _av()
    from fractions import Fraction

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"images: expected uint8 frames [T, H, W, 3], got {frames.dtype} {list(frames.shape)}")
    height, width = frames.shape[1:3]
    if height % 2 or width % 2:
        raise ValueError(f"images: expected an even height and width ({PIX_FMT} halves the colour planes), "
                         f"got {height}x{width}")
    rate = Fraction(fps).limit_denominator(1001)
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=rate, options={"crf": str(crf), "g": "2"} if codec != "mpeg4" else {})
        stream.width, stream.height, stream.pix_fmt = width, height, PIX_FMT
        for k, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts, frame.time_base = k, 1 / rate
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    return {"video.height": height, "video.width": width, "video.codec": stream.codec_context.codec.canonical_name,
            "video.pix_fmt": PIX_FMT, "video.is_depth_map": False, "video.fps": fps, "video.channels": 3,
            "has_audio": False}

