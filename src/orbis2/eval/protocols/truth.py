"""Counterfactual steering scored against the truth: the town's own rendering of each commanded path.

A real-data evaluation can only read a counterfactual's turn back from the generated frames with an
instrument; the town renders what the camera would really have seen under the command (the ``truth``
stage, :mod:`orbis2.data.truth`). Per steering mode c, beside the generated rollout from the same start:

- the per-frame error of generated against true, at ``evaluation.truth_horizons_s`` after the last
  context frame: MSE of the detail latents (the truth encoded by the detail tokenizer, normalised as the
  cache is) and PSNR of the decoded frames, each a mean over starts with a clip-bootstrap interval;
- FVD of the generated against the true counterfactual videos (paired rows, clip-bootstrap interval);
- the instrument's turn read from the true videos against the commanded turn: on the truth the video
  follows the command exactly, so this measures the instrument itself (its calibration);
- the truth-based claim (:func:`truth_claim`): the rollout under c is closer (latent MSE over the
  rollout) to the truth under c than to the truths under the other commands, by a material relative
  margin, paired per start and clip-resampled.

The starts are those of :func:`~orbis2.eval.protocols.starts.sample_ends`, which the evaluation's own samples
use too, so the truth cache and the rollouts meet on the same (clip, start) keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from orbis2.config.sections import DataConfig, EvaluationConfig
from orbis2.data.truth import TruthError, read_manifest, read_truth, truth_key
from orbis2.eval.metrics.pixels import psnr
from orbis2.eval.metrics.stats import decide, mean_interval, relative_difference
from orbis2.eval.protocols.references import fvd_with_interval
from orbis2.eval.protocols.starts import commanded_steps
from orbis2.eval.protocols.systems import Sample
from orbis2.latents import LatentCache, encode_frames
from orbis2.models.files import TokenizerFile


def horizon_frames(horizons_s: Sequence[float], fps: float, generated: int) -> dict[float, int]:
    """Horizon (s after the last context frame) -> index into the generated frames, for those a rollout of
    ``generated`` frames reaches."""
    out = {}
    for h in horizons_s:
        k = int(round(h * fps)) - 1
        if 0 <= k < generated:
            out[float(h)] = k
    return out


def latent_errors(generated: torch.Tensor, truth: torch.Tensor) -> np.ndarray:
    """Per start and frame [N, T], the mean squared difference of normalised latents [N, T, C, h, w]."""
    return (generated.float() - truth.float()).pow(2).flatten(2).mean(-1).double().numpy()


def horizon_cells(errors: np.ndarray, psnrs: np.ndarray, frames: dict[float, int], clusters: Sequence,
                  seed: int) -> list[dict[str, Any]]:
    """Per horizon the mean latent MSE and PSNR over starts with clip-bootstrap intervals."""
    cells = []
    for seconds, k in frames.items():
        mse, db = mean_interval(errors[:, k], clusters, seed=seed), mean_interval(psnrs[:, k], clusters, seed=seed)
        cells.append({"seconds": seconds, "frame": k, "latent_mse": mse.to_dict(), "psnr": db.to_dict()})
    return cells


def instrument_calibration(read_deg: np.ndarray, commanded_deg: np.ndarray, clusters: Sequence,
                           seed: int) -> dict[str, Any]:
    """The instrument's turn read from true videos against the commanded turn (degrees, each start's commanded
    direction positive): the mean reading with its interval, and the relative error (mean read - mean
    commanded) / mean commanded with its interval (0: calibrated)."""
    read = mean_interval(read_deg, clusters, seed=seed)
    commanded = float(np.mean(commanded_deg))
    relative = (relative_difference(read_deg, commanded_deg, clusters, seed=seed).to_dict()
                if abs(commanded) > 1e-9 else None)
    return {"turn_deg": read.to_dict(), "commanded_turn_deg": commanded, "relative_error": relative}


def truth_claim(distances: dict[str, dict[str, np.ndarray]], clusters: Sequence, material: float,
                seed: int) -> dict[str, Any]:
    """Is the rollout under each command closer to the truth under it than to the truths under the others?

    ``distances[c][o]`` [N]: per start, the distance of the rollout under command c to the truth under
    command o. Per command c the paired relative margin (mean over starts of the mean over o != c of
    distances[c][o], minus the mean of distances[c][c]) / the mean of distances[c][c], with a clip-bootstrap
    interval; its verdict is "holds" when the lower bound exceeds ``material`` (a fraction), "does not hold"
    when the whole interval lies below it, else unresolved. The claim holds when it holds for every command
    and fails when it fails for one. ``pairs``: the mean distance of each (c, o).
    """
    modes = list(distances)
    if len(modes) < 2:
        raise ValueError("the truth-based claim needs at least two commands")
    per_mode, verdicts = {}, []
    for c in modes:
        own = np.asarray(distances[c][c], np.float64)
        others = np.mean([np.asarray(distances[c][o], np.float64) for o in modes if o != c], axis=0)
        iv = relative_difference(others, own, clusters, seed=seed)
        verdict = decide(iv, material, kind="claim")
        verdicts.append(verdict)
        per_mode[c] = {"margin": iv.to_dict(), "own": float(own.mean()), "others": float(others.mean()),
                       "verdict": verdict}
    failed, held = "does not hold", "holds"
    overall = failed if failed in verdicts else held if all(v == held for v in verdicts) else \
        "not resolved at this sample size"
    pairs = {c: {o: float(np.mean(distances[c][o])) for o in modes} for c in modes}
    return {"material": material, "verdict": overall, "modes": per_mode, "pairs": pairs}


ENCODE_BATCH = 64  # true frames encoded at a time


class TruthScorer:
    """Scores each steering mode's rollouts against the true counterfactuals in ``root`` (the ``truth`` stage),
    mode by mode (:meth:`add`; one mode's true videos in memory at a time), then the claim (:meth:`record`).

    ``features``: I3D rows [N, 400] of videos [N, T, H, W, 3] uint8; ``read_turns``: the instrument's
    (:func:`orbis2.eval.protocols.steering.score_videos`) on videos and their controls.
    """

    def __init__(self, root: Path, samples: list[Sample], clusters: list[str], data: DataConfig,
                 ev: EvaluationConfig, steps: int, tokenizer: TokenizerFile, cache: LatentCache,
                 features: Callable[[np.ndarray], np.ndarray], read_turns: Callable[[np.ndarray, list], dict],
                 instrument: str):
        manifest = read_manifest(root)
        expected = {"split": ev.steering_split, "commanded_steps": commanded_steps(data, steps),
                    "modes": {m: [float(v) for v in scales] for m, scales in ev.steering_modes.items()},
                    "width": data.width, "height": data.height}
        found = {k: manifest.get(k) for k in expected}
        found["modes"] = {m: [float(v) for v in scales] for m, scales in (found["modes"] or {}).items()}
        stale = {k: (found[k], v) for k, v in expected.items() if found[k] != v}
        if stale:
            raise TruthError(f"{root}: rendered for other steering settings ({stale}: found, wanted); re-run the "
                             f"`truth` stage")
        self.root, self.samples, self.clusters, self.data, self.ev = Path(root), samples, clusters, data, ev
        self.tokenizer, self.cache, self.features, self.read_turns = tokenizer, cache, features, read_turns
        self.instrument = instrument
        self.generated: dict[str, torch.Tensor] = {}
        self.truth: dict[str, torch.Tensor] = {}
        self.modes: dict[str, dict[str, Any]] = {}
        self.first_video: dict[str, np.ndarray] = {}  # mode -> the first sample's true video (the figures)

    def add(self, mode: str, latents: torch.Tensor, videos: np.ndarray) -> None:
        """One mode's rollouts: normalised detail latents [N, G, ...] and decoded videos [N, 1 + G, H, W, 3] (the
        last context frame first)."""
        keys = [truth_key(s.key, s.context_end, mode) for s in self.samples]
        found = read_truth(self.root, keys)
        true = [found[k] for k in keys]
        frames = np.stack([t.frames for t in true])
        if frames.shape != videos.shape:
            raise TruthError(f"{self.root}: true videos {frames.shape[1:]} but rollouts {videos.shape[1:]} for mode "
                             f"{mode}; re-run the `truth` stage")
        flat = frames[:, 1:].reshape(-1, *frames.shape[2:])
        encoded = torch.cat([encode_frames(self.tokenizer, flat[i:i + ENCODE_BATCH])
                             for i in range(0, len(flat), ENCODE_BATCH)])
        truth = self.cache.normalize("detail", encoded.numpy().astype(np.float16)).reshape(latents.shape)
        self.generated[mode], self.truth[mode] = latents.half(), truth.half()
        self.first_video[mode] = frames[0]
        ev, seed = self.ev, self.ev.seed
        frames_at = horizon_frames(ev.truth_horizons_s, self.data.detail_hz, latents.shape[1])
        errors, psnrs = latent_errors(latents, truth), psnr(videos[:, 1:], frames[:, 1:])
        fvd = fvd_with_interval(self.features(frames), self.features(videos), self.clusters, ev.fvd_bootstrap_reps,
                                seed)
        read = self.read_turns(frames, [(t.speed, t.yaw_rate) for t in true])
        self.modes[mode] = {
            "samples": len(keys), "horizons": horizon_cells(errors, psnrs, frames_at, self.clusters, seed),
            "fvd": fvd,
            "instrument": instrument_calibration(read["turn_deg"], read["commanded_turn_deg"], self.clusters, seed),
            "collision": int(sum(t.collision.any() for t in true)),
            "off_road": int(sum(t.off_road.any() for t in true))}

    def record(self) -> dict[str, Any]:
        """Every mode's scores and the truth-based claim (latent MSE over the whole rollout, each rollout against
        each mode's truth)."""
        distances = {c: {o: latent_errors(self.generated[c], self.truth[o]).mean(axis=1) for o in self.truth}
                     for c in self.generated}
        claim = truth_claim(distances, self.clusters, self.ev.truth_margin, self.ev.seed)
        return {"instrument": self.instrument, "modes": self.modes, "claim": claim}
