"""Uncertainty for the evaluation: clip-level (cluster) bootstrap, paired effects, FVD intervals, verdicts.

Why clusters: windows and rollout starts from one clip share the scene, the
route and (for starts a fraction of a second apart) most frames, so they are not
independent; resampling them one by one would make intervals several times too
narrow. Every function here resamples whole clips (with replacement, as many as
there are) and recomputes the statistic from the resampled rows, which is the
percentile cluster bootstrap. Resamples are drawn as multiplicity weights per
clip, so one draw costs a weighted sum, not a copy of the data.

Paired effects (the same windows and noise draws under two conditions) are
resampled jointly, so the interval is that of the difference, not of two
overlapping marginal intervals. With paired noise even a negligible difference
can have an interval that excludes zero; a claim therefore needs a *material*
effect: the interval's lower bound above a stated threshold (:func:`decide`).

All functions are pure: same inputs and seed, same numbers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from orbis2.eval.metrics.fvd import frechet_distance, frechet_distance_of_rows

DEFAULT_REPS = 1000
DEFAULT_LEVEL = 0.95


@dataclass(frozen=True)
class Interval:
    """A point estimate with its percentile bootstrap interval and what it was computed from."""

    estimate: float
    low: float
    high: float
    level: float
    clusters: int
    units: int
    reps: int
    seed: int

    def to_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        return f"{self.estimate:.4g} [{self.low:.4g}, {self.high:.4g}]"


def cluster_ids(labels: Sequence) -> np.ndarray:
    """Labels (clip keys, any hashable) -> integer cluster ids 0..G-1 in order of first appearance."""
    mapping: dict[str, int] = {}
    return np.array([mapping.setdefault(str(label), len(mapping)) for label in labels], np.int64)


def cluster_weights(clusters: Sequence, reps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(integer cluster id per row [N], multiplicity of each cluster per resample [reps, G]).

    A resample draws G clusters with replacement; row weights are ``weights[:, ids]``.
    """
    ids = cluster_ids(clusters)
    n_clusters = int(ids.max()) + 1 if len(ids) else 0
    if n_clusters < 2:
        raise ValueError(f"a cluster bootstrap needs at least 2 clusters (clips), got {n_clusters}")
    rng = np.random.default_rng(seed)
    weights = rng.multinomial(n_clusters, np.full(n_clusters, 1.0 / n_clusters), size=reps).astype(np.float64)
    return ids, weights


def _interval(estimate: float, draws: np.ndarray, level: float, clusters: int, units: int, reps: int,
              seed: int) -> Interval:
    draws = draws[np.isfinite(draws)]
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(draws, [alpha, 1.0 - alpha]) if len(draws) else (np.nan, np.nan)
    return Interval(float(estimate), float(low), float(high), level, clusters, units, reps, seed)


def bootstrap_draws(clusters: Sequence, statistic: Callable[[np.ndarray], float], reps: int = DEFAULT_REPS,
                    seed: int = 0) -> tuple[float, np.ndarray, int]:
    """(full-sample statistic, its value on each clip resample [reps], number of clips).

    ``statistic(row_weights)`` gets multiplicities per row; the full sample is all ones.
    The resamples depend only on the clip labels, ``reps`` and ``seed``: two statistics
    of the same clips with the same seed see the same resamples (paired draws).
    """
    ids, weights = cluster_weights(clusters, reps, seed)
    draws = np.array([statistic(w[ids]) for w in weights], np.float64)
    return float(statistic(np.ones(len(ids)))), draws, weights.shape[1]


def interval_from_draws(estimate: float, draws: np.ndarray, clusters: int, units: int, seed: int,
                        level: float = DEFAULT_LEVEL) -> Interval:
    return _interval(estimate, np.asarray(draws, np.float64), level, clusters, units, len(draws), seed)


def bootstrap_statistic(clusters: Sequence, statistic: Callable[[np.ndarray], float], reps: int = DEFAULT_REPS,
                        level: float = DEFAULT_LEVEL, seed: int = 0) -> Interval:
    """Interval of ``statistic(row_weights)`` over clip resamples; row_weights [N] are multiplicities.

    The estimate is the statistic with every weight 1 (the full sample). Use this for
    statistics that are not means, e.g. FVD recomputed from a resample's features.
    """
    estimate, draws, n_clusters = bootstrap_draws(clusters, statistic, reps, seed)
    return _interval(estimate, draws, level, n_clusters, len(clusters), reps, seed)


def _cluster_sums(values: np.ndarray, ids: np.ndarray, n_clusters: int) -> tuple[np.ndarray, np.ndarray]:
    sums = np.bincount(ids, weights=values, minlength=n_clusters)
    counts = np.bincount(ids, minlength=n_clusters).astype(np.float64)
    return sums, counts


def _check(values: np.ndarray, clusters: Sequence, name: str) -> np.ndarray:
    values = np.asarray(values, np.float64).reshape(-1)
    if len(values) != len(clusters):
        raise ValueError(f"{name}: {len(values)} values but {len(clusters)} cluster labels")
    if not np.isfinite(values).all():
        raise ValueError(f"{name}: values must be finite")
    return values


def mean_interval(values: Sequence[float], clusters: Sequence, reps: int = DEFAULT_REPS,
                  level: float = DEFAULT_LEVEL, seed: int = 0) -> Interval:
    """The mean over units (windows, rollouts) with a clip-bootstrap interval."""
    values = _check(values, clusters, "mean_interval")
    ids, weights = cluster_weights(clusters, reps, seed)
    sums, counts = _cluster_sums(values, ids, weights.shape[1])
    draws = (weights @ sums) / (weights @ counts)
    return _interval(values.mean(), draws, level, weights.shape[1], len(values), reps, seed)


def paired_difference(a: Sequence[float], b: Sequence[float], clusters: Sequence, reps: int = DEFAULT_REPS,
                      level: float = DEFAULT_LEVEL, seed: int = 0) -> Interval:
    """mean(a - b) over paired units (same window and noise under two conditions), clips resampled jointly."""
    a, b = _check(a, clusters, "paired_difference a"), _check(b, clusters, "paired_difference b")
    return mean_interval(a - b, clusters, reps, level, seed)


def relative_difference(a: Sequence[float], b: Sequence[float], clusters: Sequence, reps: int = DEFAULT_REPS,
                        level: float = DEFAULT_LEVEL, seed: int = 0) -> Interval:
    """(mean(a) - mean(b)) / mean(b): a paired effect as a fraction of the reference ``b`` (e.g. 0.03 = 3 %)."""
    a, b = _check(a, clusters, "relative_difference a"), _check(b, clusters, "relative_difference b")
    ids, weights = cluster_weights(clusters, reps, seed)
    sums_a, _ = _cluster_sums(a, ids, weights.shape[1])
    sums_b, _ = _cluster_sums(b, ids, weights.shape[1])
    ref = weights @ sums_b
    with np.errstate(divide="ignore", invalid="ignore"):
        draws = (weights @ sums_a - ref) / ref
    return _interval((a.sum() - b.sum()) / b.sum(), draws, level, weights.shape[1], len(a), reps, seed)


# --------------------------------------------------------------------------- FVD


def weighted_moments(features: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and covariance rows R (covariance = R.T @ R, the unbiased weighted covariance)."""
    total = weights.sum()
    mean = weights @ features / total
    rows = (features - mean) * np.sqrt(weights / max(total - 1.0, 1.0))[:, None]
    return mean, rows


def fvd_statistic(real: np.ndarray, fake: np.ndarray) -> Callable[[np.ndarray], float]:
    """FVD of paired feature rows (real[i] and fake[i] from the same clip start) under row weights.

    A resample takes the same clips on both sides and recomputes both means and
    covariances, so an interval reflects which clips were evaluated, the dominant
    source of variation at tens of videos. FVD is biased upwards at small sample
    sizes, so intervals of different sample sizes are not comparable. With fewer
    videos than features the covariances are passed as rows (exact, and much
    cheaper: :func:`~orbis2.eval.metrics.fvd.frechet_distance_of_rows`).
    """
    real, fake = np.asarray(real, np.float64), np.asarray(fake, np.float64)
    if real.shape != fake.shape:
        raise ValueError(f"FVD rows must be paired: real {real.shape}, generated {fake.shape}")
    factored = real.shape[0] < real.shape[1]

    def statistic(w: np.ndarray) -> float:
        mu_r, rows_r = weighted_moments(real, w)
        mu_f, rows_f = weighted_moments(fake, w)
        if factored:
            return frechet_distance_of_rows(mu_r, rows_r, mu_f, rows_f)
        return frechet_distance(mu_r, rows_r.T @ rows_r, mu_f, rows_f.T @ rows_f)

    return statistic


def fvd_interval(real: np.ndarray, fake: np.ndarray, clusters: Sequence, reps: int = 200,
                 level: float = DEFAULT_LEVEL, seed: int = 0) -> Interval:
    """FVD of paired feature rows with a clip-bootstrap interval (see :func:`fvd_statistic`)."""
    if len(real) != len(clusters):
        raise ValueError(f"fvd_interval: {len(real)} rows but {len(clusters)} cluster labels")
    return bootstrap_statistic(clusters, fvd_statistic(real, fake), reps, level, seed)


def fvd_slope_interval(real_chunks: Sequence[np.ndarray], fake_chunks: Sequence[np.ndarray], clusters: Sequence,
                       reps: int = 200, level: float = DEFAULT_LEVEL,
                       seed: int = 0) -> tuple[list[Interval], Interval, np.ndarray]:
    """Per-chunk FVD intervals, the FVD-slope (last - first) / (chunks - 1) interval, and the slope's draws;
    every chunk is evaluated on the same clip resample."""
    if len(real_chunks) < 2 or len(real_chunks) != len(fake_chunks):
        raise ValueError("fvd_slope_interval needs at least two chunks, as many real as generated")
    n = len(real_chunks)
    results = [bootstrap_draws(clusters, fvd_statistic(r, f), reps, seed) for r, f in zip(real_chunks, fake_chunks)]
    g, units = results[0][2], len(clusters)
    chunks = [_interval(est, draws, level, g, units, reps, seed) for est, draws, _ in results]
    slope_draws = (results[-1][1] - results[0][1]) / (n - 1)
    slope = _interval((results[-1][0] - results[0][0]) / (n - 1), slope_draws, level, g, units, reps, seed)
    return chunks, slope, slope_draws


def paired_draws_interval(draws_a: Sequence[float], draws_b: Sequence[float],
                          level: float = DEFAULT_LEVEL) -> tuple[float, float]:
    """Interval of a - b from two statistics' draws on the same clip resamples (same clips, reps, seed)."""
    if len(draws_a) != len(draws_b):
        raise ValueError("paired draws need the same number of resamples on both sides")
    diff = np.asarray(draws_a, np.float64) - np.asarray(draws_b, np.float64)
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(diff, [alpha, 1.0 - alpha])
    return float(low), float(high)


# --------------------------------------------------------------------------- swaps and verdicts


def other_clip_donors(clusters: Sequence, seed: int = 0) -> np.ndarray:
    """For each unit, the index of a unit from ANOTHER clip (a derangement over clips), to take its conditioning.

    Swapping within a batch of consecutive windows (e.g. rolling by one) mostly
    hands a unit the conditioning of its own clip a fraction of a second away,
    which is nearly the right one and understates how much the model uses it.
    Clips are cyclically shifted in a random order, so no unit keeps its own clip.
    """
    ids = cluster_ids(clusters)
    n_clusters = int(ids.max()) + 1 if len(ids) else 0
    if n_clusters < 2:
        raise ValueError(f"swapping conditioning across clips needs at least 2 clips, got {n_clusters}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(n_clusters)
    target = np.empty(n_clusters, np.int64)
    target[order] = np.roll(order, -1)  # clip order[k] borrows from clip order[k+1]
    members = [np.flatnonzero(ids == c) for c in range(n_clusters)]
    donors = np.empty(len(ids), np.int64)
    for c in range(n_clusters):
        pool = members[target[c]]
        donors[members[c]] = pool[rng.integers(0, len(pool), len(members[c]))]
    check_cross_clip(clusters, donors)
    return donors


def check_cross_clip(clusters: Sequence, donors: Sequence[int]) -> None:
    """Raise if any unit would receive conditioning from its own clip."""
    ids = cluster_ids(clusters)
    same = np.flatnonzero(ids == ids[np.asarray(donors)])
    if len(same):
        raise ValueError(f"{len(same)} of {len(ids)} swapped units take their conditioning from their own clip "
                         f"(first: unit {int(same[0])}); take it from another clip")


def decide(interval: Interval, threshold: float, kind: str = "use") -> str:
    """A verdict from an interval on an effect that should be at least ``threshold`` (material).

    ``kind="use"`` (does a model use an input?): "used" when the lower bound clears
    the threshold, "not shown" otherwise. ``kind="claim"``: "holds" when the lower
    bound clears it, "does not hold" when the whole interval lies below it, and
    "not resolved at this sample size" when the interval straddles it.
    """
    if kind == "use":
        return "used" if interval.low > threshold else "not shown"
    if kind != "claim":
        raise ValueError(f"decide: kind must be 'use' or 'claim', got {kind!r}")
    if interval.low > threshold:
        return "holds"
    if interval.high < threshold:
        return "does not hold"
    return "not resolved at this sample size"
