"""Reference rows for every FVD table, and FVD records with clip-bootstrap intervals.

An FVD number means little alone: at tens of videos it is biased upwards and
varies with which clips were drawn. Every table therefore carries, on the same
clips and frames:

- ``real_floor`` (noise floor): FVD between the real continuations of two
  disjoint halves of the clips (whole episodes on either side, never a clip on
  both), over ``splits`` random half-splits (median, 2.5 % and 97.5 %
  quantiles). Each side holds half the videos, so this floor is, if anything,
  above the floor at the full sample size: a model at or below it is
  indistinguishable from real data at this sample size.
- ``reconstruction`` (ceiling): the tokenizer's decoding of the cached latents
  of the real continuation, i.e. a perfect predictor in this latent space.
- ``repeat_last`` (trivial baseline): the decoded last context frame held still.

Generated and reference FVDs come with clip-bootstrap intervals; the bootstrap
draws are stored (``draws``) so that two systems evaluated on the same clips with
the same bootstrap seed can be compared replicate by replicate (paired).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from orbis2.eval.metrics.fvd import FeatureStats, fvd
from orbis2.eval.metrics.stats import bootstrap_draws, fvd_statistic, interval_from_draws


def fvd_with_interval(real: np.ndarray, fake: np.ndarray, clusters: Sequence, reps: int, seed: int) -> dict[str, Any]:
    """FVD of paired rows with its clip-bootstrap interval and draws (same clips and seed: same resamples)."""
    estimate, draws, n_clusters = bootstrap_draws(clusters, fvd_statistic(real, fake), reps, seed)
    iv = interval_from_draws(estimate, draws, n_clusters, len(clusters), seed)
    return {"fvd": iv.estimate, "low": iv.low, "high": iv.high, "clips": iv.clusters, "videos": iv.units,
            "bootstrap_reps": reps, "bootstrap_seed": seed, "draws": [float(d) for d in draws]}


def real_floor(real: np.ndarray, clusters: Sequence, splits: int, seed: int) -> dict[str, Any]:
    """FVD between the real videos of two disjoint random halves of the clips, over ``splits`` half-splits."""
    labels = np.asarray([str(c) for c in clusters])
    unique = np.unique(labels)
    if len(unique) < 4:
        raise ValueError(f"a real-vs-real floor needs at least 4 clips (2 per half), got {len(unique)}")
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(splits):
        half = set(rng.permutation(unique)[: len(unique) // 2])
        side = np.array([label in half for label in labels])
        if side.sum() < 2 or (~side).sum() < 2:
            continue
        values.append(fvd(FeatureStats.from_features(real[side]), FeatureStats.from_features(real[~side])))
    low, median, high = np.quantile(values, [0.025, 0.5, 0.975])
    return {"fvd": float(median), "low": float(low), "high": float(high), "clips": len(unique),
            "videos_per_half": int(len(labels) // 2), "half_splits": len(values), "seed": seed,
            "definition": "FVD between the real continuations of two disjoint random halves of the clips"}


def reference_rows(real: np.ndarray, reconstruction: np.ndarray, repeat_last: np.ndarray, clusters: Sequence,
                   reps: int, seed: int, splits: int = 50) -> dict[str, dict[str, Any]]:
    """The three reference rows of one FVD table (see the module docstring); with fewer than 4 clips the
    floor is recorded as not computable (``fvd`` None, with the reason)."""
    clips = len(set(map(str, clusters)))
    rows: dict[str, dict[str, Any]] = {"real_floor": real_floor(real, clusters, splits, seed) if clips >= 4 else
                                       {"fvd": None, "clips": clips, "reason": "needs at least 4 clips (2 per half)"}}
    rows["reconstruction"] = fvd_with_interval(real, reconstruction, clusters, reps, seed)
    rows["repeat_last"] = fvd_with_interval(real, repeat_last, clusters, reps, seed)
    return rows
