"""The ``orbis2`` command: use trained models.

``orbis2 rollout`` reads the context from any video, rolls the hierarchical
model forward and writes an mp4 and a GIF. User-fixable problems (short video,
bad trajectory CSV, missing or mismatched checkpoints) print one message naming
the file and the fix and exit with status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from orbis2.config import load_config
from orbis2.data.importer import read_odometry_csv
from orbis2.data.video import probe, read_video, resample_stride, write_video
from orbis2.errors import OrbisError
from orbis2.io import atomic_file
from orbis2.kinematics import integrate_odometry
from orbis2.latents import encode_frames
from orbis2.models.stdit import PredictorFile, load_predictor
from orbis2.models.tokenizer import TokenizerFile, load_tokenizer
from orbis2.registry import layout_path
from orbis2.rollout import cascaded_rollout, first_context_end, rollout_schedule, steering_sequences

DEFAULT_ACTION = layout_path("predictor", "action") / "predictor.pt"
DEFAULT_ABSTRACT_TF = layout_path("predictor", "abstract_tf") / "predictor.pt"
# Steering inputs are divided by these (m/s, rad/s) unless the predictor's meta["steering"]["scale"] records its own.
DEFAULT_STEERING_SCALE = (10.0, 0.5)


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


def load_steering(args: argparse.Namespace, video: Path) -> tuple[dict[str, np.ndarray] | None, Path | None]:
    """Odometry from --trajectory, else the video's own CSV next to it, else none (unconditional)."""
    path = args.trajectory or (video.with_suffix(".csv") if video.with_suffix(".csv").is_file() else None)
    if path is None:
        return None, None
    if not path.is_file():
        raise OrbisError(f"{path}: trajectory file not found; pass an existing CSV with columns timestamp, speed, "
                         f"yaw_rate")
    return read_odometry_csv(path), path


def read_context(video: Path, cfg, needed: int) -> np.ndarray:
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


# --------------------------------------------------------------------------- drawing


def _to_uint8(images: torch.Tensor) -> np.ndarray:
    """[N, 3, H, W] in [-1, 1] -> RGB uint8 [N, H, W, 3]."""
    return ((images.clamp(-1, 1) + 1) * 127.5).round().byte().permute(0, 2, 3, 1).cpu().numpy()


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
    """``out`` (mp4) and the GIF with the same stem; both written atomically."""
    with atomic_file(out) as tmp:
        write_video(tmp, frames, fps)
    gif = out.with_suffix(".gif")
    with atomic_file(gif) as tmp:
        images = [Image.fromarray(f) for f in frames]
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                       duration=round(1000 / fps), loop=0)
    return gif


# --------------------------------------------------------------------------- rollout command


def rollout_command(args: argparse.Namespace) -> str:
    cfg = load_config(args.params, args.profile)
    data = cfg.data
    steps = max(1, math.ceil(args.seconds * data.abstract_hz))
    context_end = first_context_end(data)
    schedule = rollout_schedule(data, context_end, steps)
    frames = read_context(args.video, cfg, context_end + 1)
    odometry, odometry_path = load_steering(args, args.video)

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    detail_tok = load_tokenizer(args.detail_tokenizer, device)
    abstract_tok = load_tokenizer(args.abstract_tokenizer, device)
    abstract_path = abstract_predictor_path(args.abstract_predictor)
    abstract_pred = load_predictor(abstract_path, device)
    detail_pred = load_predictor(args.detail_predictor, device)
    check_pairing(abstract_pred, abstract_path, abstract_tok, "abstract", args.abstract_tokenizer)
    check_pairing(detail_pred, args.detail_predictor, detail_tok, "detail", args.detail_tokenizer)
    check_pairing(detail_pred, args.detail_predictor, abstract_tok, "abstract", args.abstract_tokenizer)

    steering = path = None
    if odometry is not None:
        if abstract_pred.model.steering is None:
            raise OrbisError(f"{abstract_path}: this abstract predictor is not steered but {odometry_path} gives a "
                             f"trajectory; train the action stage or drop --trajectory")
        last = schedule[-1].detail_target[-1]
        t = np.arange(last + 1) / data.fps
        speed = np.interp(t, odometry["timestamp"], odometry["speed"]) * args.speed_scale
        yaw_rate = np.interp(t, odometry["timestamp"], odometry["yaw_rate"]) * args.yaw_rate_scale
        speed_norm, yaw_rate_norm = (abstract_pred.meta.get("steering") or {}).get("scale", DEFAULT_STEERING_SCALE)
        steering = steering_sequences(schedule, speed, yaw_rate, speed_norm, yaw_rate_norm)
        steering = steering[None].to(device)
        x, y, _ = integrate_odometry(speed[context_end:], yaw_rate[context_end:], data.fps)
        path = (x, y)

    first = schedule[0]
    detail_ctx = encode_frames(detail_tok, frames[list(first.detail_context)]) * detail_tok.scale
    abstract_ctx = encode_frames(abstract_tok, frames[list(first.abstract_context)]) * abstract_tok.scale
    generator = torch.Generator(device=device).manual_seed(args.seed)
    with tqdm(total=steps, desc="rollout", unit="step") as bar:
        details, _ = cascaded_rollout(
            abstract_pred.model, detail_pred.model, detail_ctx[None].to(device), abstract_ctx[None].to(device),
            steps, generator, abstract_nfe=args.abstract_nfe, detail_nfe=args.detail_nfe,
            abstract_hz=data.abstract_hz, detail_hz=data.detail_hz, steering=steering,
            on_step=lambda _: bar.update(1))

    generated = []
    with torch.inference_mode():
        for chunk in details[0].split(8):
            generated.append(_to_uint8(detail_tok.model.decode(chunk / detail_tok.scale)))
    context_frames = frames[list(first.detail_context)]
    video = np.concatenate([context_frames, np.concatenate(generated)])
    indices = np.array(list(first.detail_context) + [i for s in schedule for i in s.detail_target])
    real = None
    if args.side_by_side:
        real = np.zeros_like(video)
        available = indices < len(frames)
        real[available] = frames[indices[available]]
    out = compose(video, real, path, np.clip(indices - context_end, 0, None))
    gif = write_outputs(args.out, out, data.detail_hz)
    mode = "unconditional" if steering is None else f"steered by {odometry_path}"
    return f"wrote {args.out} and {gif}: {len(out)} frames at {data.detail_hz} Hz, {steps} steps, {mode}"


def add_rollout_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rollout", help="roll the hierarchical world model forward from a video's context")
    p.add_argument("--video", type=Path, required=True, help="context video (any rate that is a multiple of data.fps)")
    p.add_argument("--trajectory", type=Path, default=None,
                   help="CSV with columns timestamp, speed, yaw_rate (default: <video>.csv if present)")
    p.add_argument("--speed-scale", type=float, default=1.0, help="multiply the speeds (counterfactuals)")
    p.add_argument("--yaw-rate-scale", type=float, default=1.0, help="multiply the yaw rates (counterfactuals)")
    p.add_argument("--seconds", type=float, default=16.0, help="rollout length in seconds")
    p.add_argument("--out", type=Path, required=True, help="output mp4; a GIF with the same stem is written too")
    p.add_argument("--detail-tokenizer", type=Path, default=layout_path("tokenizer", "detail") / "tokenizer.pt")
    p.add_argument("--abstract-tokenizer", type=Path, default=layout_path("tokenizer", "abstract") / "tokenizer.pt")
    p.add_argument("--abstract-predictor", type=Path, default=None,
                   help=f"default: {DEFAULT_ACTION}, else {DEFAULT_ABSTRACT_TF}")
    p.add_argument("--detail-predictor", type=Path, default=layout_path("predictor", "detail") / "predictor.pt")
    p.add_argument("--params", type=Path, default=Path("params.yaml"))
    p.add_argument("--profile", default=None, help="smoke | default | paper (default: the file's `profile`)")
    p.add_argument("--side-by-side", action="store_true", help="show the real continuation on the left")
    p.add_argument("--abstract-nfe", type=int, default=15)
    p.add_argument("--detail-nfe", type=int, default=30)
    p.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(run=rollout_command)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="orbis2", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    add_rollout_parser(sub)
    args = parser.parse_args(argv)
    try:
        print(args.run(args))
    except OrbisError as err:
        print(f"orbis2 {args.command}: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
