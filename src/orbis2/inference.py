"""Trained models in use: what ``orbis2 rollout`` (:mod:`orbis2.cli`) and ``orbis2 play`` (:mod:`orbis2.drive`)
share.

Loading the tokenizers and predictors with their pairing checks, reading a video's context, steering files,
the sampler's settings, decoding latents and writing the videos. Functions take plain values, not the command's
options, so that both commands (and tests) call them alike. User-fixable problems raise
:class:`~orbis2.errors.OrbisError` naming the file and the fix; the command prints it and exits with status 2.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import torch

from orbis2.accel import compile_decoder, compile_predictor, inference_autocast
from orbis2.config.params import PROFILES, PipelineConfig, load_config
from orbis2.data.episodes import read_odometry
from orbis2.data.images import to_uint8
from orbis2.data.importer import read_odometry_csv
from orbis2.data.video import probe, read_video, resample_stride, write_gif, write_video
from orbis2.errors import OrbisError
from orbis2.io import atomic_file
from orbis2.models.files import PredictorFile, TokenizerFile, load_predictor, load_tokenizer
from orbis2.registry import layout_path, registry
from orbis2.tasks.official import built_from_import, check_imported

DEFAULT_ACTION = layout_path("predictor", registry().steered) / "predictor.pt"
DEFAULT_ABSTRACT_TF = layout_path("predictor", "abstract_tf") / "predictor.pt"


# --------------------------------------------------------------------------- loading and checks


def abstract_predictor_path(given: Path | None) -> Path:
    """The action (steered) predictor, else the teacher-forced abstract one; an explicit path is used as is."""
    if given is not None:
        return given
    if DEFAULT_ACTION.is_file() or not DEFAULT_ABSTRACT_TF.is_file():
        return DEFAULT_ACTION
    return DEFAULT_ABSTRACT_TF


def check_pairing(predictor: PredictorFile, path: Path, tokenizer: TokenizerFile, kind: str, tok_path: Path) -> None:
    """The predictor must have been trained on this tokenizer's latents (checksum when recorded, else channels)."""
    recorded = (predictor.meta.get("tokenizers") or {}).get(kind)
    checksum = recorded.get("checksum") if isinstance(recorded, dict) else recorded
    if checksum is not None and checksum != tokenizer.checksum:
        raise OrbisError(
            f"{path}: trained on the {kind} tokenizer with checksum {checksum[:12]}, but {tok_path} has "
            f"{tokenizer.checksum[:12]}; pass the matching --{kind}-tokenizer or retrain the predictor"
        )
    if tokenizer.kind != kind:
        raise OrbisError(f"{tok_path}: is a {tokenizer.kind} tokenizer; pass the {kind} one")


def load_checkpoints(detail_tokenizer: Path, abstract_tokenizer: Path, abstract_predictor: Path | None,
                     detail_predictor: Path, device: str | None, cfg: PipelineConfig, params: Path
                     ) -> tuple[TokenizerFile, TokenizerFile, Path, PredictorFile, PredictorFile]:
    """Both tokenizers and predictors on ``device`` (None: cuda if available, else cpu), refused if unreadable,
    made for another profile than ``cfg``'s (``params`` names the one they fit) or not trained on these
    tokenizers; the abstract predictor's path is :func:`abstract_predictor_path`'s and is returned with them."""
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    abstract_path = abstract_predictor_path(abstract_predictor)
    loaded = []
    for path, load in ((detail_tokenizer, load_tokenizer), (abstract_tokenizer, load_tokenizer),
                       (abstract_path, load_predictor), (detail_predictor, load_predictor)):
        try:
            loaded.append(load(path, device))
        except OrbisError:
            raise
        except (OSError, RuntimeError, KeyError, TypeError, ValueError, pickle.UnpicklingError, EOFError) as err:
            raise OrbisError(f"{path}: not a checkpoint this version can read ({type(err).__name__}: "
                             f"{str(err).splitlines()[0][:200]}); pass the file a training stage wrote") from err
    detail_tok, abstract_tok, abstract_pred, detail_pred = loaded
    frame = (cfg.data.height, cfg.data.width)
    for tok, path in ((detail_tok, detail_tokenizer), (abstract_tok, abstract_tokenizer)):
        size = tuple(tok.model.encoder.image_size)
        if size != frame:
            raise OrbisError(f"{path}: made for {size[1]}x{size[0]} frames but profile {cfg.profile} uses "
                             f"{frame[1]}x{frame[0]}; pass {profile_hint(params, size)}or that profile's "
                             f"checkpoints")
    for pred, path, stage in ((abstract_pred, abstract_path, "abstract_tf"),
                              (detail_pred, detail_predictor, "detail")):
        preset, wanted = pred.build.get("preset"), cfg.section(stage).preset
        if preset != wanted and not built_from_import(pred.meta):
            raise OrbisError(f"{path}: a {preset!r} predictor but profile {cfg.profile} uses {wanted!r}; pass the "
                             f"profile it was trained with (--profile) or that profile's checkpoints")
    check_imported(abstract_pred, abstract_path, cfg, "abstract")
    check_imported(detail_pred, detail_predictor, cfg, "detail")
    check_pairing(abstract_pred, abstract_path, abstract_tok, "abstract", abstract_tokenizer)
    check_pairing(detail_pred, detail_predictor, detail_tok, "detail", detail_tokenizer)
    check_pairing(detail_pred, detail_predictor, abstract_tok, "abstract", abstract_tokenizer)
    return detail_tok, abstract_tok, abstract_path, abstract_pred, detail_pred


def profile_hint(params: Path, size: tuple[int, int]) -> str:
    """``--profile P `` for the profile whose frames have ``size`` (height, width), if one has."""
    for profile in PROFILES:
        data = load_config(params, profile).data
        if (data.height, data.width) == size:
            return f"--profile {profile} "
    return ""


def compile_models(abstract_pred: PredictorFile, detail_pred: PredictorFile, detail_tok: TokenizerFile) -> None:
    """``--compile``: both predictors by region and the detail decoder (each shape compiles on first use)."""
    compile_predictor(abstract_pred.model)
    compile_predictor(detail_pred.model)
    compile_decoder(detail_tok.model)


def sampler_settings(abstract_nfe: int | None, detail_nfe: int | None, guidance: float | None, cfg: PipelineConfig,
                     detail_pred: PredictorFile, steered: bool) -> tuple[int, int, float, str]:
    """Abstract and detail Euler steps and the steering guidance a rollout samples with, and a line saying so.

    The values given (``--abstract-nfe``, ``--detail-nfe``, ``--steering-guidance``), else the sampler the run's
    evaluation scored these models with (params.yaml's ``evaluation`` of the profile: 4 and 6 steps with
    guidance 3 at the default profile, the paper's 15 and 30 without guidance at ``paper``), so that what a user
    rolls out or drives is what the report measured. A distilled detail predictor's own steps come before the
    evaluation's; guidance applies to a steered rollout.
    """
    ev = cfg.evaluation
    given = [flag for flag, value in (("--abstract-nfe", abstract_nfe), ("--detail-nfe", detail_nfe),
                                      ("--steering-guidance", guidance)) if value is not None]
    abstract_nfe = abstract_nfe or ev.top_nfe
    detail_nfe = detail_nfe or detail_pred.nfe(ev.bottom_nfe)
    guidance = guidance if guidance is not None else ev.steering_guidance
    guidance = guidance if steered else 1.0
    why = f"given {', '.join(given)}; otherwise " if given else ""
    line = (f"sampler: {abstract_nfe} abstract / {detail_nfe} detail Euler steps, steering guidance {guidance:g} "
            f"({why}evaluation.{cfg.profile}'s)")
    return abstract_nfe, detail_nfe, guidance, line


def consistency_grid(predictor: PredictorFile, path: Path, nfe: int | None) -> list[float] | None:
    """The noise levels a consistency-distilled predictor (the authors' distilled abstract one) samples ``nfe``
    steps on (None: its own count), from the grids its file records; None for a predictor sampled with Euler."""
    sampling = predictor.meta.get("sampling", {})
    if sampling.get("method") != "consistency":
        return None
    steps = str(nfe or sampling.get("nfe", 4))
    grids = sampling["grids"]
    if steps not in grids:
        raise OrbisError(f"{path}: a consistency-distilled predictor with grids for {', '.join(grids)} steps, not "
                         f"{steps}; pass --abstract-nfe with one of them")
    return [float(level) for level in grids[steps]]


# --------------------------------------------------------------------------- context and steering


def read_context(video: Path, cfg: PipelineConfig, needed: int) -> np.ndarray:
    """Every native frame of the video, resampled and resized with the importer's rules."""
    info = probe(video)
    stride = resample_stride(info.fps, cfg.data.fps, cfg.import_.fps_tolerance, video)
    frames = read_video(video, stride, (cfg.data.width, cfg.data.height))
    if len(frames) < needed:
        raise OrbisError(
            f"{video}: {len(frames)} frames at {cfg.data.fps} fps ({len(frames) / cfg.data.fps:.2f} s) but the "
            f"rollout needs {needed} frames ({needed / cfg.data.fps:.2f} s) of context for the 2 Hz abstract "
            f"window; use a longer video"
        )
    return frames


def load_steering(trajectory: Path | None, video: Path) -> tuple[dict[str, np.ndarray] | None, Path | None]:
    """Odometry from ``trajectory`` (``--trajectory``), else the video's own CSV or episode parquet next to it,
    else none (unconditional). A parquet is the raw-episode layout of `town` and `import` (columns t, speed,
    yaw_rate)."""
    beside = [video.with_suffix(s) for s in (".csv", ".parquet") if video.with_suffix(s).is_file()]
    path = trajectory or (beside[0] if beside else None)
    if path is None:
        return None, None
    if not path.is_file():
        raise OrbisError(f"{path}: trajectory file not found; pass an existing CSV with columns timestamp, speed, "
                         f"yaw_rate (or an episode's .parquet)")
    if path.suffix == ".parquet":
        odometry = read_odometry(path)
        return {"timestamp": odometry["t"], "speed": odometry["speed"], "yaw_rate": odometry["yaw_rate"]}, path
    return read_odometry_csv(path), path


def steering_until(odometry: dict[str, np.ndarray], path: Path, t_end: float, hold_last: bool) -> None:
    """The trajectory must cover the rollout from the first context frame to ``t_end`` s (or hold its last value)."""
    first, last = float(odometry["timestamp"][0]), float(odometry["timestamp"][-1])
    if first > 1e-9:
        raise OrbisError(f"{path}: starts at {first:g} s but the rollout's context starts at 0 s; timestamps are "
                         f"seconds from the video's first frame")
    if last < t_end - 1e-9 and not hold_last:
        raise OrbisError(f"{path}: ends at {last:g} s but this rollout needs steering up to {t_end:g} s; give a "
                         f"longer trajectory, a shorter --seconds, or --hold-last to keep its last values")


# --------------------------------------------------------------------------- decoding, drawing and writing


def decode_latents(tokenizer: TokenizerFile, latents: torch.Tensor, device: torch.device,
                   precision: str) -> np.ndarray:
    """Scaled detail latents [T, ...] -> RGB uint8 frames, decoded 8 at a time (``orbis2 play`` records through
    this too, so its recordings match the rollout's frames bit for bit)."""
    generated = []
    with torch.inference_mode(), inference_autocast(device, precision):
        for chunk in latents.split(8):
            generated.append(to_uint8(tokenizer.model.decode(tokenizer.denormalize(chunk))))
    return np.concatenate(generated)


def draw_path_inset(frame: np.ndarray, x: np.ndarray, y: np.ndarray, current: int) -> np.ndarray:
    """A small top-down view of the steering path (x forward = up, y left = left) with the current position."""
    out = frame.copy()
    size = max(24, min(frame.shape[:2]) // 3)
    span = max(float(np.abs(np.concatenate([x, y])).max()), 1.0)
    px = (size / 2 - y / span * size / 2 * 0.9).astype(np.int32)
    py = (size - 2 - x / span * (size - 4)).astype(np.int32)
    h, w = frame.shape[:2]
    x0, y0 = w - size - 2, 2
    region = out[y0:y0 + size, x0:x0 + size]
    region[:] = (region * 0.4).astype(np.uint8)
    points = np.stack([px, py], axis=1).reshape(-1, 1, 2)
    cv2.polylines(region, [points], False, (80, 200, 255), 1, cv2.LINE_AA)
    cv2.circle(region, (int(px[current]), int(py[current])), 2, (255, 80, 80), -1, cv2.LINE_AA)
    return out


def compose(generated: np.ndarray, real: np.ndarray | None, path: tuple[np.ndarray, np.ndarray] | None,
            path_index: np.ndarray) -> np.ndarray:
    """Output frames: generated (with the path inset), real continuation on the left when given."""
    frames = []
    for i, frame in enumerate(generated):
        if path is not None:
            frame = draw_path_inset(frame, path[0], path[1], int(path_index[i]))
        if real is not None:
            frame = np.concatenate([real[i], frame], axis=1)
        frames.append(frame)
    return np.stack(frames)


def write_outputs(out: Path, frames: np.ndarray, fps: float) -> Path:
    """``out`` (mp4) and the GIF with the same stem; both written atomically, the folder made if needed."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        write_video(tmp, frames, fps, playable=True)
    gif = out.with_suffix(".gif")
    with atomic_file(gif) as tmp:
        write_gif(tmp, frames, fps)
    return gif
