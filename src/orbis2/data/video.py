"""Video files through OpenCV (PyAV where OpenCV cannot decode): probing, reading, writing,
frame-rate resampling by timestamps; GIFs through Pillow.

Frames are RGB ``uint8`` arrays ``[H, W, 3]`` everywhere in the library; the BGR
order OpenCV uses stays inside this module.

Reading goes through OpenCV first (fast, and what wrote our own files) and falls back to
PyAV when OpenCV cannot open a file or decodes no frame from it: OpenCV's wheels carry an
FFmpeg without an AV1 decoder (AV1 files open and decode to zero frames), while PyAV's
wheels carry FFmpeg with dav1d (AV1), HEVC, VP9 and H.264 decoders, are self-contained (no
system FFmpeg, no subprocess) and give each frame's presentation time. A container whose
header lies about its frame count (a webm without a duration reports about -2.8e17) is
probed as "count unknown" (0), and :func:`count_frames` counts by demuxing.

Two codecs are written: videos people watch (rollouts, previews) as VP9, which
browsers and MLflow's artifact view play (OpenCV's wheels carry libvpx, but no
H.264 encoder); the dataset's own episodes as MPEG-4 Part 2 (``mp4v``), which
encodes fast and which every OpenCV build reads, but which browsers do not play.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterable, Iterator

import av
import cv2
import numpy as np
from PIL import Image

from orbis2.errors import OrbisError

# Beyond this a container's frame count is a lie (a day of 1000-fps video), not a count.
MAX_PLAUSIBLE_FRAMES = 10**8

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
# FourCC of the codec OpenCV writes for the dataset (fast, any OpenCV reads it; read back, OpenCV names it FMP4).
DATASET_CODEC = "mp4v"
PLAYABLE_SUFFIXES = (".mp4", ".webm")  # the containers VP9 is written into (read back, OpenCV names it VP90)
# VP9 for people (browsers play it), encoded by libvpx through PyAV at its real-time speed setting and a constant
# quality: OpenCV's writer offers no speed setting, and its default took 7x longer for the evaluation's sample
# videos (1536 x 288 at the smoke profile) at the same quality (PSNR within 1 dB on a worst-case texture).
PLAYABLE_OPTIONS = {"deadline": "realtime", "cpu-used": "8", "crf": "20", "b": "0"}


class VideoError(OrbisError):
    """A video cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class VideoInfo:
    path: Path
    fps: float
    frames: int  # as reported by the container, 0 when it reports none or nonsense; verified when decoding
    width: int
    height: int
    codec: str = ""  # as the reader names it (FourCC from OpenCV, FFmpeg's decoder name from PyAV)


def printable(path: Path) -> str:
    """The path as text even when its name is not valid UTF-8 (undecodable bytes shown as ``\\xNN``)."""
    return str(path).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def open_capture(path: Path) -> cv2.VideoCapture:
    """An opened ``cv2.VideoCapture``, or a :class:`VideoError` naming the file and the fix.

    Checks what OpenCV would otherwise crash on or misread: a name that is not valid
    UTF-8 (OpenCV's Python binding crashes the process on it), a missing file, a
    folder, a file OpenCV cannot decode. Decodes on one thread: the data stages run one
    part per core, and FFmpeg's own threads only made parts side by side contend (at
    512x288, the same frames/s on one thread with 20 % less CPU).
    """
    name = _video_name(path)
    if not Path(path).is_file():
        problem = "is a folder" if Path(path).is_dir() else "does not exist"
        raise VideoError(f"{name}: {problem}; pass an existing video file")
    cap = cv2.VideoCapture(name, cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, 1])
    if not cap.isOpened():
        cap.release()
        raise VideoError(f"{name}: cannot open this file with OpenCV or PyAV (unreadable or not a video); "
                         f"re-encode it as mp4 (e.g. ffmpeg -i {Path(path).name} out.mp4) or remove it")
    return cap


def _video_name(path: Path) -> str:
    """``str(path)``, refused if not valid UTF-8: OpenCV's Python binding crashes the process on such names, and
    PyAV's writer cannot encode them either."""
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise VideoError(f"{printable(path)}: the file name is not valid UTF-8, which OpenCV and PyAV cannot handle; "
                         f"rename the file (e.g. convmv -f latin1 -t utf8 --notest)") from None
    return name


def plausible_count(frames: float) -> int:
    """A container's frame count, 0 (unknown) when it is negative or absurd."""
    return int(frames) if 0 < frames < MAX_PLAUSIBLE_FRAMES else 0


def probe(path: Path) -> VideoInfo:
    """Rate, size, codec and announced frame count; through PyAV when OpenCV cannot open the file."""
    _video_name(path)  # a name that is not UTF-8 is refused for every reader alike
    try:
        cap = open_capture(path)
    except VideoError:
        info = _pyav_probe(path)
        if info is None:
            raise
    else:
        try:
            code = int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
            info = VideoInfo(
                path=Path(path),
                fps=float(cap.get(cv2.CAP_PROP_FPS) or 0.0),
                frames=plausible_count(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0),
                width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                codec=code.to_bytes(4, "little").decode("ascii", "replace"),
            )
        finally:
            cap.release()
        if info.fps <= 0:
            info = _pyav_probe(path) or info
    if info.fps <= 0:
        raise VideoError(f"{path}: the container reports no frame rate; re-encode it with a fixed rate")
    return info


def _pyav_probe(path: Path) -> VideoInfo | None:
    """What PyAV reads from the container's first video stream, or None when it cannot open the file."""
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate or 0
            return VideoInfo(Path(path), float(rate), plausible_count(stream.frames or 0),
                             stream.codec_context.width, stream.codec_context.height, stream.codec_context.name)
    except (av.FFmpegError, IndexError, OSError):
        return None


def codec_name(path: Path) -> str:
    """The video codec's name for messages (FFmpeg's name where PyAV can read the container)."""
    info = _pyav_probe(path)
    return info.codec if info is not None else "unknown"


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


def iter_timed_frames(path: Path) -> Iterator[tuple[float, np.ndarray]]:
    """Every frame as (seconds from the first frame, RGB), by its presentation time.

    OpenCV decodes when it can; a file it cannot open, or from which it decodes no frame
    (AV1 in OpenCV's wheels), is decoded by PyAV. When neither decodes a frame the error
    names the codec. A time that does not increase (a container without timestamps) is
    replaced by the previous one plus one period of the announced rate.
    """
    _video_name(path)
    try:
        cap = open_capture(path)
    except VideoError:
        if _pyav_probe(path) is None:
            raise
        cap = None
    decoded = 0
    if cap is not None:
        period = 1.0 / (cap.get(cv2.CAP_PROP_FPS) or 30.0)
        try:
            first = last = None
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                first = t if first is None else first
                t = t - first if last is None or t - first > last else last + period
                last = t
                decoded += 1
                yield t, cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        finally:
            cap.release()
    if decoded == 0:
        yield from _pyav_frames(path)


def _pyav_frames(path: Path) -> Iterator[tuple[float, np.ndarray]]:
    decoded = 0
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            period = 1.0 / float(stream.average_rate or stream.guessed_rate or 30)
            first = last = None
            for frame in container.decode(stream):
                t = frame.time if frame.time is not None else (last or 0.0) + period
                first = t if first is None else first
                t = t - first if last is None or t - first > last else last + period
                last = t
                decoded += 1
                yield t, frame.to_ndarray(format="rgb24")
    except (av.FFmpegError, IndexError, OSError) as err:
        if decoded:
            return  # a truncated tail: the frames before it are kept, the caller checks the count
        raise VideoError(f"{printable(path)}: no frame could be decoded from its {codec_name(path)} video stream "
                         f"by OpenCV or PyAV ({err}); re-encode it (e.g. ffmpeg -i {Path(path).name} -c:v libx264 "
                         f"out.mp4) or remove it") from None
    if decoded == 0:
        raise VideoError(f"{printable(path)}: no frame could be decoded from its {codec_name(path)} video stream "
                         f"(empty or truncated, or a codec neither OpenCV nor PyAV decodes); re-encode it (e.g. "
                         f"ffmpeg -i {Path(path).name} -c:v libx264 out.mp4) or remove it")


def iter_frames(path: Path, stride: int = 1, size: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
    """Decode every ``stride``-th frame as RGB, resized (cover + centre crop) to ``size=(W, H)``."""
    for index, (_, rgb) in enumerate(iter_timed_frames(path)):
        if index % stride == 0:
            yield rgb if size is None else resize_cover(rgb, size)


def count_frames(path: Path) -> int:
    """The number of frames, counted by reading the stream (for containers whose header lies).

    OpenCV grabs without converting; a file it decodes nothing from is counted by PyAV's demuxer
    (one packet per frame)."""
    count = 0
    try:
        cap = open_capture(path)
    except VideoError:
        cap = None
    if cap is not None:
        try:
            while cap.grab():
                count += 1
        finally:
            cap.release()
    if count:
        return count
    try:
        with av.open(str(path)) as container:
            return sum(1 for packet in container.demux(container.streams.video[0]) if packet.size)
    except (av.FFmpegError, IndexError, OSError) as err:
        raise VideoError(f"{printable(path)}: cannot read its video stream ({err}); replace the file") from None


@dataclass(frozen=True)
class Resampled:
    """Frames taken at a fixed rate from a video at any rate, and how far each is from its slot."""

    frames: np.ndarray  # [N, H, W, 3] RGB, frame k standing for time k / fps
    source_times: np.ndarray  # seconds from the first source frame of the frame kept for each slot
    source_frames: int  # frames decoded from the source
    source_fps: float  # from the decoded timestamps
    max_error_s: float  # largest |source time - k / fps|



def read_resampled(path: Path, fps: float, size: tuple[int, int] | None = None) -> Resampled:
    """The video at ``fps`` by timestamps, all in memory (:func:`iter_resampled`, which streams it)."""
    stats: dict[str, float] = {}
    pairs = list(iter_resampled(path, fps, size, stats))
    return Resampled(np.stack([frame for _, frame in pairs]), np.array([t for t, _ in pairs]),
                     int(stats["source_frames"]), stats["source_fps"], stats["max_error_s"])


def iter_resampled(path: Path, fps: float, size: tuple[int, int] | None = None,
                   stats: dict[str, float] | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """The video at ``fps`` by timestamps, slot by slot: for each slot k / fps up to the last frame, the
    nearest source frame, as (its source time, RGB resized to ``size``). Holds two frames at a time.

    Nearest frame rather than blending neighbours: a blend is a picture no camera took
    (ghosted edges the tokenizer would learn), while the nearest frame is off in time by at
    most half a source period (20 ms at 25 fps), which is recorded. Works for any source
    rate at or above ``fps`` (23.976, 24, 25, 29.97, 30, 50, 60 ...) and for variable
    rates; a source slower than ``fps``, or a gap of more than one slot, would repeat
    frames and is refused, once the whole video is read (the error ends the iteration).
    When it ends, ``stats`` holds ``source_frames`` (decoded), ``source_fps`` (from the
    decoded timestamps) and ``max_error_s`` (the largest |source time - k / fps|).
    """
    stats = {} if stats is None else stats
    previous: tuple[float, np.ndarray] | None = None
    k = decoded = 0
    worst = (0.0, 0, 0.0)  # error, slot, source time

    def keep(t: float, frame: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal worst
        error = abs(t - k / fps)
        if error > worst[0]:
            worst = (error, k, t)
        return t, frame if size is None else resize_cover(frame, size)

    for t, frame in iter_timed_frames(path):
        decoded += 1
        while k / fps <= t + 1e-9:
            target = k / fps
            yield keep(*previous) if previous is not None and target - previous[0] <= t - target else keep(t, frame)
            k += 1
        previous = (t, frame)
    if k == 0:
        raise VideoError(f"{printable(path)}: no frame could be decoded (empty or truncated video)")
    last_t = previous[0] if previous is not None else 0.0
    source_fps = (decoded - 1) / last_t if decoded > 1 and last_t > 0 else fps
    stats.update(source_frames=decoded, source_fps=source_fps, max_error_s=worst[0])
    if k > 1 and worst[0] > 0.5 / fps + 1e-6:
        why = (f"the source runs at {source_fps:.3f} fps, slower than {fps:g}" if source_fps < fps * 0.99 else
               f"the source has a gap near {worst[2]:.2f} s")
        raise VideoError(f"{printable(path)}: {why}: the frame for {worst[1] / fps:.2f} s would be "
                         f"{worst[0] * 1000:.0f} ms off (over half a period at {fps:g} fps) and frames would "
                         f"repeat; use a source at {fps:g} fps or faster, or lower data.fps")


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
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if playable:
        return _write_playable(path, frames, fps)
    codec = "FFV1" if lossless else DATASET_CODEC
    writer = None
    count = 0
    try:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                writer = cv2.VideoWriter(_video_name(path), cv2.VideoWriter_fourcc(*codec), float(fps), (w, h))
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


def _write_playable(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """VP9 (``PLAYABLE_OPTIONS``) in the container the suffix names; returns the number of frames written."""
    count = 0
    with av.open(_video_name(path), "w") as container:
        stream = None
        for frame in frames:
            if stream is None:
                stream = container.add_stream("libvpx-vp9", rate=Fraction(fps).limit_denominator(1001),
                                               options=PLAYABLE_OPTIONS)
                stream.height, stream.width = frame.shape[:2]
                stream.pix_fmt, stream.thread_count = "yuv420p", 1
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")))
            count += 1
        if stream is not None:
            container.mux(stream.encode())
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
    scaled down to ``width`` pixels when given. The caller makes the write atomic.

    Each frame gets its own 256-colour palette by Pillow's fast octree: its default (median cut) took 9x as long
    for the evaluation's sample videos, for 0.6 dB more PSNR against the RGB frames (36.4 against 35.8 dB).
    """
    images = []
    for frame in frames:
        image = Image.fromarray(frame)
        if width and image.width > width:
            image = image.resize((width, max(1, round(image.height * width / image.width))), Image.Resampling.LANCZOS)
        images.append(image.quantize(256, method=Image.Quantize.FASTOCTREE))
    if not images:
        raise VideoError(f"{printable(path)}: no frames to write")
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return len(images)
