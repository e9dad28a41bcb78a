"""Do the trained predictors beat trivial baselines, and does steering steer?

Run from the project root after the DAG has trained the predictors::

    python tools/predictor_sanity.py --profile default [--seconds 4] [--split val]

1. Rollout vs. copy: the paper's cascaded rollout from each clip's first possible
   context (2 s at 2 Hz ending on frame 20) for ``--seconds``, compared with the
   true detail latents of the cache (per-frame MSE), against the trivial
   prediction that repeats the last context frame.
2. Steering: rollouts of the same ``turns`` contexts with the clip's own yaw-rate
   sequence scaled by 0.5 and by 1.5, decoded with the detail tokenizer; the
   statistic is the mean horizontal optical flow (Farneback) signed by the
   direction of the true turn. A model that steers turns harder under x1.5, so
   the scene sweeps sideways faster.
Prints one line per figure; the numbers are what the closing notes quote.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from orbis2.config import load_config
from orbis2.latents import open_cache
from orbis2.models.stdit import load_predictor
from orbis2.models.tokenizer import load_tokenizer
from orbis2.rollout import cascaded_rollout, first_context_end, rollout_schedule, steering_sequences


def clip_tensors(cache, split, data, context_end, steps):
    """Detail/abstract contexts, true future detail latents and odometry of every clip long enough."""
    arrays, index = cache.arrays(split), cache.index(split)
    schedule = rollout_schedule(data, context_end, steps)
    detail_ctx, abstract_ctx, future, odometry = [], [], [], []
    need = schedule[-1].detail_target[-1] + 1
    for entry in index.values():
        if entry["length"] < need:
            continue
        o = entry["offset"]
        detail_ctx.append(arrays["detail"][o + np.array(schedule[0].detail_context)])
        abstract_ctx.append(arrays["abstract"][o + np.array(schedule[0].abstract_context)])
        targets = np.concatenate([s.detail_target for s in schedule])
        future.append(arrays["detail"][o + targets])
        odometry.append(arrays["odometry"][o : o + need])
    as_tensor = lambda xs, kind: torch.from_numpy(np.stack(xs).astype(np.float32)) * cache.scale(kind)
    return (as_tensor(detail_ctx, "detail"), as_tensor(abstract_ctx, "abstract"), as_tensor(future, "detail"),
            np.stack(odometry), schedule)


def horizontal_flow(frames: np.ndarray) -> float:
    """Mean horizontal Farneback flow (pixels/frame) over consecutive RGB uint8 frames."""
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    flows = [cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 15, 3, 5, 1.2, 0)[..., 0].mean()
             for a, b in zip(grey[:-1], grey[1:])]
    return float(np.mean(flows))


def decode(tokenizer, latents: torch.Tensor) -> np.ndarray:
    b, f = latents.shape[:2]
    images = tokenizer.model.decode(latents.flatten(0, 1) / tokenizer.scale)
    images = ((images.clamp(-1, 1) + 1) * 127.5).round().byte().permute(0, 2, 3, 1).numpy()
    return images.reshape(b, f, *images.shape[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--profile", default=None)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--split", default="val")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cfg = load_config(args.params, args.profile)
    data = cfg.data
    detail_tok = load_tokenizer(Path("data/tokenizers/detail/tokenizer.pt"))
    abstract_tok = load_tokenizer(Path("data/tokenizers/abstract/tokenizer.pt"))
    cache = open_cache(Path("data/latents"), detail_tok.checksum, abstract_tok.checksum)
    abstract_tf = load_predictor(Path("data/predictors/abstract_tf/predictor.pt")).model
    action = load_predictor(Path("data/predictors/action/predictor.pt"))
    detail = load_predictor(Path("data/predictors/detail/predictor.pt")).model
    steps = round(args.seconds * data.abstract_hz)
    context_end = first_context_end(data)

    detail_ctx, abstract_ctx, future, _, _ = clip_tensors(cache, args.split, data, context_end, steps)
    generator = torch.Generator().manual_seed(args.seed)
    predicted, _ = cascaded_rollout(abstract_tf, detail, detail_ctx, abstract_ctx, steps, generator)
    model_mse = ((predicted - future) ** 2).mean(dim=(0, 2, 3, 4))
    copy_mse = ((detail_ctx[:, -1:] - future) ** 2).mean(dim=(0, 2, 3, 4))
    print(f"rollout vs copy on {args.split} ({len(future)} clips, {args.seconds:g} s, {len(model_mse)} frames): "
          f"latent MSE model {model_mse.mean():.4f} vs repeat-last-frame {copy_mse.mean():.4f}")
    print("  per second (model / copy): " + ", ".join(
        f"{m:.3f}/{c:.3f}" for m, c in zip(model_mse.view(-1, data.detail_hz).mean(1),
                                           copy_mse.view(-1, data.detail_hz).mean(1))))

    detail_ctx, abstract_ctx, _, odometry, schedule = clip_tensors(cache, "turns", data, context_end, steps)
    speed_norm, yaw_norm = action.meta["steering"]["scale"]
    turn_sign = np.sign(odometry[:, context_end:, 1].mean(axis=1))
    stats = {}
    for scale in (0.5, 1.5):
        steering = torch.stack([steering_sequences(schedule, o[:, 0], o[:, 1] * scale, speed_norm, yaw_norm)
                                for o in odometry])
        generator = torch.Generator().manual_seed(args.seed)
        predicted, _ = cascaded_rollout(action.model, detail, detail_ctx, abstract_ctx, steps, generator,
                                        steering=steering)
        frames = decode(detail_tok, predicted)
        stats[scale] = np.array([horizontal_flow(f) for f in frames]) * turn_sign
    agree = float(np.mean(stats[1.5] > stats[0.5]))
    print(f"steering on turns ({len(turn_sign)} clips): signed horizontal flow x0.5 {stats[0.5].mean():.3f} "
          f"vs x1.5 {stats[1.5].mean():.3f} px/frame; x1.5 sweeps faster in {agree:.0%} of clips")


if __name__ == "__main__":
    main()
