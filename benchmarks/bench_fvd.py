"""The FVD stage's three costs on a CPU, old way against new way, side by side in one run.

    python benchmarks/bench_fvd.py [--preset default] [--videos 64] [--reps 200] [--decode-videos 4]
        [--seconds 6] [--i3d-clips 8] [--json out.json]

* Clip bootstrap of one FVD: ``--reps`` resamples of ``--videos`` paired I3D feature
  rows (400-d). Covariances as 400 x 400 matrices through ``frechet_distance`` (two
  eigendecompositions per resample) against covariance rows through
  ``frechet_distance_of_rows`` (one videos x videos SVD); the largest relative
  difference of the two FVDs is reported with them.
* Decoding generated videos for the FVD windows of one short split (``--seconds`` at
  10 Hz): every frame, then I3D's 16 per window picked, against decoding only those
  16 (``PickedFrames``), with the detail tokenizer of ``--preset`` (random weights:
  the time depends on the size only). The clips must agree to one grey level (other
  batches of frames round differently in the last bits of float32).
* I3D on ``--i3d-clips`` 16-frame clips at 224 x 224 (random weights, channels-last as
  ``i3d_features`` runs it), three ways: its units as first ported (a zero-padded copy, the
  convolution, then the batch norm; every max pool on a -inf-padded copy); the batch norm
  folded into the convolution and SAME padding left to the operators, every unit a
  convolution; and as it runs, the pointwise units a matrix product over the channels-last
  memory (``Unit3D.forward``), which matters on one thread.

Times are medians of 3 runs after a warm-up, with the torch threads the process has.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Callable
from unittest import mock

import numpy as np
import torch
import torch.nn.functional as F

from orbis2.eval.metrics.fvd import even_frame_indices, frechet_distance
from orbis2.eval.metrics.stats import cluster_weights, fvd_statistic, weighted_moments
from orbis2.eval.protocols.rollout_fvd import PickedFrames
from orbis2.models import i3d
from orbis2.models.tokenizer import build_detail_tokenizer

FEATURES, FPS = 400, 10


def median_seconds(fn: Callable[[], object], runs: int = 3) -> float:
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def bootstrap(videos: int, reps: int) -> dict:
    rng = np.random.default_rng(0)
    real = rng.normal(size=(videos, FEATURES))
    fake = real + rng.normal(scale=0.5, size=(videos, FEATURES))
    ids, weights = cluster_weights(np.arange(videos) // 2, reps, seed=0)
    rows = [w[ids] for w in weights]

    def covariances() -> list[float]:
        out = []
        for w in rows:
            (mu_r, r), (mu_f, f) = weighted_moments(real, w), weighted_moments(fake, w)
            out.append(frechet_distance(mu_r, r.T @ r, mu_f, f.T @ f))
        return out

    statistic = fvd_statistic(real, fake)
    old, new = np.array(covariances()), np.array([statistic(w) for w in rows])
    t_old, t_new = median_seconds(covariances), median_seconds(lambda: [statistic(w) for w in rows])
    return {"videos": videos, "resamples": reps, "covariance_s": t_old, "rows_s": t_new,
            "speedup": t_old / t_new, "max_relative_difference": float(np.max(np.abs(old - new) / old))}


class Decoder:
    """What ``PickedFrames`` needs of a system: frame-by-frame decoding to uint8 video."""

    def __init__(self, preset: str):
        self.model = build_detail_tokenizer(preset).eval()

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> np.ndarray:
        b, t = latents.shape[:2]
        images = torch.cat([self.model.decode(part) for part in latents.flatten(0, 1).split(16)])
        frames = ((images + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1)
        return frames.numpy().reshape(b, t, *frames.shape[1:])


def decoding(preset: str, videos: int, seconds: float) -> dict:
    system = Decoder(preset)
    frames = round(seconds * FPS)
    grid = (160 // 16, 256 // 16) if preset != "smoke" else (72 // 8, 128 // 8)
    latents = torch.randn(videos, frames, system.model.decoder.conv_in.in_channels, *grid)
    window = slice(0, frames)
    picks = even_frame_indices(frames)
    every = lambda: system.decode(latents)[:, picks]  # noqa: E731
    picked = lambda: PickedFrames(system, latents, [window]).clip(window)  # noqa: E731
    # Other batches of frames round differently in the last float bits: at most a grey level here and there.
    difference = int(np.abs(every().astype(int) - picked().astype(int)).max())
    if difference > 1:
        raise AssertionError(f"decoding the picked frames differs from decoding every frame by {difference} levels")
    t_old, t_new = median_seconds(every), median_seconds(picked)
    return {"preset": preset, "videos": videos, "frames_per_video": frames, "every_frame_s": t_old,
            "picked_frames_s": t_new, "speedup": t_old / t_new, "max_difference_levels": difference}


def padded_unit(unit: i3d.Unit3D, x: torch.Tensor) -> torch.Tensor:
    """The unit as first ported: SAME zero padding as a copy, the convolution, then the batch norm."""
    x = unit.conv(i3d._same_pad(x, unit.kernel, unit.stride, 0.0))
    bn = unit.bn
    return F.relu(F.batch_norm(x, bn.running_mean, bn.running_var, None, bn.bias, False, 0.0, i3d.BN_EPS))


def padded_pool(x: torch.Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> torch.Tensor:
    return F.max_pool3d(i3d._same_pad(x, kernel, stride, float("-inf")), kernel, stride)


def convolved_unit(unit: i3d.Unit3D, x: torch.Tensor) -> torch.Tensor:
    """The unit with its batch norm folded, every kernel size a convolution (pointwise ones included)."""
    return F.relu_(unit.convolution(x, *unit.folded()))


def i3d_units(clips: int) -> dict:
    model = i3d.InceptionI3d().eval().to(memory_format=torch.channels_last_3d)
    video = torch.rand(clips, 3, 16, 224, 224) * 2 - 1
    video = video.contiguous(memory_format=torch.channels_last_3d)

    @torch.inference_mode()
    def pointwise_matmul() -> torch.Tensor:
        return model(video)

    @torch.inference_mode()
    def folded() -> torch.Tensor:
        with mock.patch.object(i3d.Unit3D, "forward", convolved_unit):
            return model(video)

    @torch.inference_mode()
    def padded() -> torch.Tensor:
        with mock.patch.object(i3d.Unit3D, "forward", padded_unit), mock.patch.object(i3d, "_max_pool_same",
                                                                                      padded_pool):
            return model(video)

    now, convolved, first = pointwise_matmul(), folded(), padded()
    t_first, t_folded, t_now = median_seconds(padded), median_seconds(folded), median_seconds(pointwise_matmul)
    return {"clips": clips, "padded_s": t_first, "folded_s": t_folded, "pointwise_matmul_s": t_now,
            "speedup": t_first / t_folded, "pointwise_speedup": t_folded / t_now,
            "max_logit_difference": float((convolved - first).abs().max()),
            "pointwise_max_logit_difference": float((now - convolved).abs().max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default", help="detail tokenizer preset (default: %(default)s)")
    parser.add_argument("--videos", type=int, default=64, help="videos per FVD (default: %(default)s)")
    parser.add_argument("--reps", type=int, default=200, help="bootstrap resamples (default: %(default)s)")
    parser.add_argument("--decode-videos", type=int, default=4, help="videos decoded (default: %(default)s)")
    parser.add_argument("--seconds", type=float, default=6.0, help="video length (default: %(default)s)")
    parser.add_argument("--i3d-clips", type=int, default=8, help="clips through I3D (default: %(default)s)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()
    result = {"threads": torch.get_num_threads(), "bootstrap": bootstrap(args.videos, args.reps),
              "decoding": decoding(args.preset, args.decode_videos, args.seconds),
              "i3d": i3d_units(args.i3d_clips)}
    b, d, u = result["bootstrap"], result["decoding"], result["i3d"]
    print(f"bootstrap, {b['videos']} videos x {b['resamples']} resamples: covariances {b['covariance_s']:.2f} s, "
          f"rows {b['rows_s']:.3f} s ({b['speedup']:.0f}x; largest relative difference "
          f"{b['max_relative_difference']:.1e})")
    print(f"decoding {d['videos']} videos of {d['frames_per_video']} frames ({d['preset']}): every frame "
          f"{d['every_frame_s']:.2f} s, the 16 I3D reads {d['picked_frames_s']:.2f} s ({d['speedup']:.1f}x; largest "
          f"difference {d['max_difference_levels']} grey level)")
    print(f"I3D on {u['clips']} clips: padded copies and a separate batch norm {u['padded_s']:.2f} s, folded "
          f"{u['folded_s']:.2f} s ({u['speedup']:.2f}x; largest logit difference {u['max_logit_difference']:.1e}), "
          f"pointwise units as a matrix product {u['pointwise_matmul_s']:.2f} s ({u['pointwise_speedup']:.2f}x "
          f"the folded; largest logit difference {u['pointwise_max_logit_difference']:.1e})")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
