"""The learned inverse-dynamics instrument: speed and yaw rate from consecutive frames (the ``inverse_dynamics`` stage).

Monocular visual odometry needs trackable texture and a consistent scene; on
generated video it mostly returns noise, so the steering evaluation could not
tell a steered model from an unsteered one. This instrument is a small CNN
(:class:`orbis2.models.inverse_dynamics.InverseDynamicsNet`) trained on the
town's train split to regress the controls over [t, t + 1) from the dense optical
flow between frames t and t + 1 at the native rate (OpenCV Farneback: a fixed,
texture-agnostic front end, so a few hundred frames suffice). Horizontal flips
(with the yaw rate negated) double the data and make left and right symmetric;
:mod:`orbis2.tasks.instrument` trains it with the shared loop (``orbis2.train``),
resumably. The stage reports val R^2 on real frames,
on the detail tokenizer's reconstructions of those frames (what the instrument
sees of a perfect world model), and a shuffled control (frame t paired with a
random frame of the same clip: no consistent motion, R^2 near zero or below).

Registered as ``evaluation.inverse_dynamics: learned``
(:data:`orbis2.eval.metrics.odometry.INVERSE_DYNAMICS`): a video's per-step predictions are
integrated into a planar trajectory in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from orbis2.accel import conv_layout
from orbis2.data.images import to_uint8
from orbis2.data.shards import iter_clips
from orbis2.errors import OrbisError
from orbis2.kinematics import integrate_controls
from orbis2.latents import encode_frames
from orbis2.models.files import load_tokenizer
from orbis2.models.inverse_dynamics import InverseDynamicsNet

# The file the ``inverse_dynamics`` stage publishes in its output folder (what ``evaluation.inverse_dynamics:
# learned`` loads).
WEIGHTS_FILE = "model.pt"


@dataclass
class ClipFrames:
    """Per clip: frames at the instrument's resolution [T, h, w, 3] uint8, odometry [T, 2], the clip key."""

    frames: list[np.ndarray]
    odometry: list[np.ndarray]
    keys: list[str]


def resize(frames: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return np.ascontiguousarray(frames)
    h, w = frames.shape[1:3]
    size = (max(8, round(w * scale)), max(8, round(h * scale)))
    return np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames])


def load_clips(shards: Path, split: str, scale: float, max_clips: int | None = None) -> ClipFrames:
    """Every clip of ``split`` of the shards in ``shards`` with odometry (at most ``max_clips``, evenly spread),
    frames resized by ``scale``."""
    clips = list(iter_clips(shards, split))
    clips = [c for c in clips if c.meta["has_odometry"]]
    if max_clips is not None and len(clips) > max_clips:
        clips = [clips[int(i)] for i in np.linspace(0, len(clips) - 1, max_clips).round()]
    if not clips:
        raise OrbisError(f"{shards}: the {split} split has no clip with odometry; the inverse-dynamics instrument "
                         f"trains on the town's (or imported) speed and yaw rate")
    return ClipFrames([resize(c.frames(np.arange(len(c))), scale) for c in clips],
                      [np.asarray(c.odometry, np.float64) for c in clips], [c.key for c in clips])


def pair_index(data: ClipFrames) -> np.ndarray:
    """(clip, t) of every consecutive pair whose controls over [t, t + 1) are known."""
    rows = [(c, t) for c, odo in enumerate(data.odometry) for t in range(len(odo) - 1) if np.isfinite(odo[t]).all()]
    return np.array(rows, np.int64).reshape(-1, 2)


def pair_flow(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Dense optical flow (Farneback) [N, 2, h, w] float32 from each ``first[i]`` to ``second[i]`` (uint8 RGB),
    written into one array (no list of fields and copies of it beside it)."""
    out = np.empty((len(first), 2, *np.shape(first)[1:3]), np.float32)
    for i, (a, b) in enumerate(zip(first, second)):
        ga, gb = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)
        out[i] = cv2.calcOpticalFlowFarneback(ga, gb, None, 0.5, 3, 9, 3, 5, 1.1, 0).transpose(2, 0, 1)
    return out


def to_input(first: np.ndarray, second: np.ndarray, device: torch.device) -> torch.Tensor:
    """Two uint8 stacks [N, h, w, 3] -> their flow fields [N, 2, h, w] as a tensor on ``device``."""
    return torch.from_numpy(pair_flow(first, second)).to(device)


@dataclass
class Instrument:
    """A trained network with the standardisation of its targets and the frame rate and scale it expects."""

    net: InverseDynamicsNet
    mean: np.ndarray
    std: np.ndarray
    fps: float
    scale: float

    @torch.no_grad()
    def predict(self, first: np.ndarray, second: np.ndarray, batch: int = 64) -> np.ndarray:
        """Controls [N, 2] (m/s, rad/s) between frames ``first[i]`` and ``second[i]`` (already at its scale)."""
        dev = next(self.net.parameters()).device
        self.net.eval()
        out = [self.net(to_input(first[s:s + batch], second[s:s + batch], dev)).cpu().double().numpy()
               for s in range(0, len(first), batch)]
        return np.concatenate(out) * self.std + self.mean

    def __call__(self, frames: np.ndarray, K: np.ndarray) -> np.ndarray:
        """The :class:`orbis2.eval.metrics.odometry.InverseDynamics` interface: a video [T, H, W, 3] -> positions
        [T, 2]."""
        small = resize(np.asarray(frames), self.scale)
        controls = self.predict(small[:-1], small[1:])
        return integrate_controls(controls[:, 0], controls[:, 1], 1.0 / self.fps)

    def save(self, path: Path, meta: dict[str, Any]) -> None:
        torch.save({"state": self.net.state_dict(), "width": self.net.head.in_features // 4,
                    "mean": self.mean.tolist(), "std": self.std.tolist(), "fps": self.fps, "scale": self.scale,
                    "meta": meta}, path)

    @classmethod
    def load(cls, path: Path, device: str | torch.device = "cpu") -> Instrument:
        if not Path(path).is_file():
            raise OrbisError(f"{path}: missing; run the `inverse_dynamics` stage first (evaluation.inverse_dynamics "
                             f"= learned needs it)")
        state = torch.load(path, map_location=device, weights_only=True)
        net = conv_layout(InverseDynamicsNet(state["width"])).to(device)
        net.load_state_dict(state["state"])
        return cls(net, np.array(state["mean"]), np.array(state["std"]), state["fps"], state["scale"])


def r2(y: np.ndarray, pred: np.ndarray) -> list[float | None]:
    """Coefficient of determination per column; None where the targets do not vary (e.g. a val split
    without turns has no yaw-rate variance, and R^2 is undefined)."""
    out: list[float | None] = []
    for k in range(y.shape[1]):
        total = float(((y[:, k] - y[:, k].mean()) ** 2).sum())
        out.append(None if total <= 1e-9 * len(y) else 1.0 - float(((y[:, k] - pred[:, k]) ** 2).sum()) / total)
    return out


def evaluate_instrument(instrument: Instrument, data: ClipFrames, max_pairs: int, seed: int,
                        reconstructed: ClipFrames | None = None) -> dict[str, Any]:
    """Val R^2 (speed, yaw rate) on real pairs, on reconstructed frames, and on shuffled pairs (the control)."""
    index = pair_index(data)
    if len(index) > max_pairs:
        index = index[np.linspace(0, len(index) - 1, max_pairs).round().astype(int)]
    y = np.stack([data.odometry[c][t] for c, t in index])
    rng = np.random.default_rng(seed)

    def score(frames: list[np.ndarray], partner) -> dict[str, float | None]:
        first = np.stack([frames[c][t] for c, t in index])
        second = np.stack([frames[c][partner(c, t)] for c, t in index])
        pred = instrument.predict(first, second)
        speed, yaw = r2(y, pred)
        rmse = np.sqrt(((y - pred) ** 2).mean(axis=0))
        return {"speed_r2": speed, "yaw_rate_r2": yaw, "speed_rmse": float(rmse[0]), "yaw_rate_rmse": float(rmse[1])}

    out = {"pairs": len(index), "clips": len(set(index[:, 0].tolist())),
           "real": score(data.frames, lambda c, t: t + 1),
           "shuffled": score(data.frames, lambda c, t: int(rng.integers(0, len(data.frames[c]))))}
    if reconstructed is not None:
        out["reconstructed"] = score(reconstructed.frames, lambda c, t: t + 1)
    return out


def reconstruct(tokenizer_file: Path, shards: Path, split: str, data: ClipFrames, scale: float, device: torch.device,
                chunk: int = 32) -> ClipFrames:
    """The same clips (of ``split`` in ``shards``) through the tokenizer of ``tokenizer_file`` (encode, decode)
    at full resolution, then resized."""
    tokenizer = load_tokenizer(tokenizer_file, device)
    clips = {c.key: c for c in iter_clips(shards, split) if c.key in set(data.keys)}
    frames = []
    for key in data.keys:
        full = clips[key].frames(np.arange(len(clips[key])))
        parts = []
        with torch.inference_mode():
            for s in range(0, len(full), chunk):
                image = tokenizer.model.decode(encode_frames(tokenizer, full[s:s + chunk]).to(device))
                parts.append(to_uint8(image))
        frames.append(resize(np.concatenate(parts), scale))
    return ClipFrames(frames, data.odometry, data.keys)
