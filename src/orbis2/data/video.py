"""Video files through OpenCV: probing, reading, writing, frame-rate resampling; GIFs through Pillow.

Frames are RGB ``uint8`` arrays ``[H, W, 3]`` everywhere in the library; the BGR
order OpenCV uses stays inside this module.

Two codecs are written: videos people watch (rollouts, previews) as VP9, which
browsers and MLflow's artifact view play (OpenCV's wheels carry libvpx, but no
H.264 encoder); the dataset's own episodes as MPEG-4 Part 2 (``mp4v``), which
encodes fast and which every OpenCV build reads, but which browsers do not play.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np
from PIL import Image

from orbis2.errors import OrbisError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
# FourCC of the codec written: for people (browsers play it) and for the dataset (fast, any OpenCV reads it).
PLAYABLE_CODEC, DATASET_CODEC = "vp09", "mp4v"  # read back, OpenCV names them VP90 and FMP4
PLAYABLE_SUFFIXES = (".mp4", ".webm")  # the containers VP9 is written into


class VideoError(OrbisError):
    """A video cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class VideoInfo:
    path: Path
    fps: float
    frames: int  # as reported by the container; verified when decoding
    width: int
    height: int


def printable(path: Path) -> str:
    """The path as text even when its name is not valid UTF-8 (undecodable bytes shown as ``\\xNN``)."""
    return str(path).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def open_capture(path: Path) -> cv2.VideoCapture:
    """An opened ``cv2.VideoCapture``, or a :class:`VideoError` naming the file and the fix.

    Checks what OpenCV would otherwise crash on or misread: a name that is not valid
    UTF-8 (OpenCV's Python binding crashes the process on it), a missing file, a
    folder, a file OpenCV cannot decode.
    """
    name = _opencv_name(path)
    if not Path(path).is_file():
        problem = "is a folder" if Path(path).is_dir() else "does not exist"
        raise VideoError(f"{name}: {problem}; pass an existing video file")
    cap = cv2.VideoCapture(name)
    if not cap.isOpened():
        cap.release()
        raise VideoError(f"{name}: OpenCV cannot open this file (unreadable or not a video); re-encode it as "
                         f"mp4 (e.g. ffmpeg -i {Path(path).name} out.mp4) or remove it")
    return cap


def _opencv_name(path: Path) -> str:
    """``str(path)``, refused if not valid UTF-8: OpenCV's Python binding crashes the process on such names."""
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise VideoError(f"{printable(path)}: the file name is not valid UTF-8, which OpenCV cannot handle; rename "
                         f"the file (e.g. convmv -f latin1 -t utf8 --notest)") from None
    return name


def probe(path: Path) -> VideoInfo:
    cap = open_capture(path)
    try:
        info = VideoInfo(
            path=Path(path),
            fps=float(cap.get(cv2.CAP_PROP_FPS) or 0.0),
            frames=int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0),
            width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
    finally:
        cap.release()
    if info.fps <= 0:
        raise VideoError(f"{path}: the container reports no frame rate; re-encode it with a fixed rate")
    return info


def resample_stride(source_fps: float, target_fps: int, tolerance: float, path: Path) -> int:
    """Keep every ``stride``-th frame; only integer ratios are exact, so only those are allowed.

    ``tolerance`` is relative slack for rates such as 29.97 (NTSC), taken as 30.
    """
    ratio = source_fps / target_fps
    stride = round(ratio)
    if stride < 1 or abs(ratio - stride) > tolerance * stride:
        raise VideoError(
            f"{path}: frame rate {source_fps:.3f} fps is not an integer multiple of the configured "
            f"native rate {target_fps} fps; re-encode it (e.g. ffmpeg -r {target_fps * max(stride, 1)}) "
            f"or change data.fps in params.yaml"
        )
    return stride


def iter_frames(path: Path, stride: int = 1, size: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
    """Decode every ``stride``-th frame as RGB, resized (cover + centre crop) to ``size=(W, H)``."""
    cap = open_capture(path)
    try:
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if index % stride == 0:
                rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
                yield rgb if size is None else resize_cover(rgb, size)
            index += 1
    finally:
        cap.release()


def read_video(path: Path, stride: int = 1, size: tuple[int, int] | None = None) -> np.ndarray:
    frames = list(iter_frames(path, stride, size))
    if not frames:
        raise VideoError(f"{path}: no frame could be decoded (empty or truncated video)")
    return np.stack(frames)


def resize_cover(frame: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """Scale so the frame covers ``size=(W, H)``, then centre-crop (keeps the aspect ratio).

    ``nearest`` samples without blending, for label maps (class ids, depth).
    """
    width, height = size
    h, w = frame.shape[:2]
    if (w, h) == (width, height):
        return frame
    scale = max(width / w, height / h)
    new_w, new_h = max(width, round(w * scale)), max(height, round(h * scale))
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(frame, (new_w, new_h), interpolation=interp)
    x0, y0 = (new_w - width) // 2, (new_h - height) // 2
    return np.ascontiguousarray(resized[y0 : y0 + height, x0 : x0 + width])


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float, playable: bool = False,
                lossless: bool = False) -> int:
    """Write RGB frames; ``playable``: VP9 (``.mp4`` or ``.webm``), for videos people watch in a
    browser; ``lossless``: FFV1 in Matroska (``.mkv``), frames that read back bit for bit, which a
    reproducible score needs; else MPEG-4 Part 2 (``mp4v``), for the dataset's episodes.

    Returns the number of frames written. The caller makes the write atomic.
    """
    if playable and lossless:
        raise ValueError("a video is either playable (VP9) or lossless (FFV1)")
    if lossless and Path(path).suffix != ".mkv":
        raise VideoError(f"{printable(path)}: lossless (FFV1) videos are written as .mkv; name the file <name>.mkv")
    if playable and Path(path).suffix.lower() not in PLAYABLE_SUFFIXES:
        raise VideoError(f"{printable(path)}: a video to watch is written as .mp4 or .webm (VP9); "
                         f"change the file name's suffix")
    codec = "FFV1" if lossless else PLAYABLE_CODEC if playable else DATASET_CODEC
    writer = None
    count = 0
    try:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                writer = cv2.VideoWriter(_opencv_name(path), cv2.VideoWriter_fourcc(*codec), float(fps), (w, h))
                if not writer.isOpened():
                    raise VideoError(f"{printable(path)}: OpenCV cannot write {codec} video here (its build has no "
                                     f"such encoder, or the folder is not writable); install the "
                                     f"opencv-python-headless wheel, which includes libvpx")
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            count += 1
    finally:
        if writer is not None:
            writer.release()
    return count


def codec_of(path: Path) -> str:
    """The FourCC of a video's codec as OpenCV reports it (``VP90``, ``mp4v``, ``avc1``, ...)."""
    cap = open_capture(path)
    try:
        code = int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
    finally:
        cap.release()
    return code.to_bytes(4, "little").decode("ascii", "replace")


def write_gif(path: Path, frames: Iterable[np.ndarray], fps: float, width: int | None = None) -> int:
    """Write RGB frames as a looping GIF (a thumbnail that plays wherever an image shows),
    scaled down to ``width`` pixels when given. The caller makes the write atomic."""
    images = []
    for frame in frames:
        image = Image.fromarray(frame)
        if width and image.width > width:
            image = image.resize((width, max(1, round(image.height * width / image.width))), Image.Resampling.LANCZOS)
        images.append(image)
    if not images:
        raise VideoError(f"{printable(path)}: no frames to write")
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return len(images)
