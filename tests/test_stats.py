"""Clip-bootstrap intervals cover known values at about their level; swaps never stay in the clip; verdicts."""

import numpy as np
import pytest

from orbis2.eval.metrics.fvd import frechet_distance
from orbis2.eval.metrics.stats import (
    Interval,
    check_cross_clip,
    cluster_ids,
    decide,
    fvd_interval,
    fvd_slope_interval,
    fvd_statistic,
    mean_interval,
    other_clip_donors,
    paired_difference,
    relative_difference,
)


def clustered(rng, clips=24, per_clip=4, mean=1.0, clip_sd=1.0, unit_sd=0.5):
    """Values with a shared per-clip offset: units of a clip are strongly correlated."""
    offsets = rng.normal(0.0, clip_sd, clips)
    values = mean + np.repeat(offsets, per_clip) + rng.normal(0.0, unit_sd, clips * per_clip)
    return values, np.repeat([f"clip{i}" for i in range(clips)], per_clip)


def test_cluster_ids_follow_first_appearance():
    assert cluster_ids(["b", "b", "a", "c", "a"]).tolist() == [0, 0, 1, 2, 1]


def test_mean_interval_covers_the_true_mean_at_its_level():
    rng = np.random.default_rng(0)
    hits = 0
    for rep in range(200):
        values, clips = clustered(rng)
        iv = mean_interval(values, clips, reps=400, seed=rep)
        hits += iv.low <= 1.0 <= iv.high
    assert 0.88 <= hits / 200 <= 0.99


def test_unit_level_resampling_would_undercover_clustered_data():
    """The reason for clusters: treating each unit as its own clip gives too-narrow intervals."""
    rng = np.random.default_rng(1)
    hits = 0
    for rep in range(200):
        values, _ = clustered(rng, clip_sd=1.0, unit_sd=0.1)
        iv = mean_interval(values, np.arange(len(values)), reps=400, seed=rep)
        hits += iv.low <= 1.0 <= iv.high
    assert hits / 200 < 0.8


def test_paired_difference_covers_a_known_effect():
    rng = np.random.default_rng(2)
    hits = 0
    for rep in range(200):
        base, clips = clustered(rng)
        effect = base + 0.3 + rng.normal(0, 0.2, len(base))
        iv = paired_difference(effect, base, clips, reps=400, seed=rep)
        hits += iv.low <= 0.3 <= iv.high
    assert 0.88 <= hits / 200 <= 0.99


def test_relative_difference_estimate_and_determinism():
    rng = np.random.default_rng(3)
    b, clips = clustered(rng, mean=10.0)
    a = 1.2 * b
    iv = relative_difference(a, b, clips, seed=5)
    assert iv.estimate == pytest.approx(0.2)
    assert iv.low == pytest.approx(0.2) and iv.high == pytest.approx(0.2)
    assert mean_interval(a, clips, seed=9) == mean_interval(a, clips, seed=9)


def test_bootstrap_needs_two_clips_and_matching_lengths():
    with pytest.raises(ValueError, match="at least 2 clusters"):
        mean_interval([1.0, 2.0], ["a", "a"])
    with pytest.raises(ValueError, match="cluster labels"):
        mean_interval([1.0, 2.0, 3.0], ["a", "b"])


def test_other_clip_donors_never_stay_in_the_clip():
    clips = np.repeat(["a", "b", "c", "d", "e"], [3, 1, 4, 2, 5])
    for seed in range(20):
        donors = other_clip_donors(clips, seed)
        assert (clips[donors] != clips).all()


def test_rolling_consecutive_windows_by_one_is_rejected():
    """The trap: a batch of consecutive windows rolled by one mostly swaps in the same clip's subgoal."""
    clips = np.repeat(["a", "b", "c"], 6)
    rolled = np.roll(np.arange(len(clips)), 1)
    with pytest.raises(ValueError, match="own clip"):
        check_cross_clip(clips, rolled)
    with pytest.raises(ValueError, match="at least 2 clips"):
        other_clip_donors(["a", "a", "a"])


def _iv(low, high):
    return Interval((low + high) / 2, low, high, 0.95, 10, 40, 100, 0)


def test_decide_needs_a_material_lower_bound():
    # Excludes zero but not material: paired noise can make tiny effects "significant".
    assert decide(_iv(0.001, 0.01), 0.03) == "not shown"
    assert decide(_iv(0.05, 0.2), 0.03) == "used"
    assert decide(_iv(0.05, 0.2), 0.03, "claim") == "holds"
    assert decide(_iv(-0.1, 0.02), 0.03, "claim") == "does not hold"
    assert decide(_iv(0.0, 0.1), 0.03, "claim") == "not resolved at this sample size"
    with pytest.raises(ValueError):
        decide(_iv(0, 1), 0.0, "maybe")


def test_fvd_interval_is_zero_for_identical_sets_and_grows_with_a_shift():
    rng = np.random.default_rng(4)
    clips = np.repeat(np.arange(20), 4)
    real = rng.normal(size=(80, 6))
    same = fvd_interval(real, real.copy(), clips, reps=50, seed=1)
    assert same.estimate == pytest.approx(0.0, abs=1e-6) and same.high == pytest.approx(0.0, abs=1e-6)
    shifted = fvd_interval(real, real + 2.0, clips, reps=50, seed=1)
    # Mean shift of 2 in 6 dimensions: FVD = 6 * 4 = 24 exactly on every resample.
    assert shifted.estimate == pytest.approx(24.0, rel=1e-6) and shifted.low == pytest.approx(24.0, rel=1e-6)


@pytest.mark.parametrize("videos, dim", [(24, 50), (60, 8)])
def test_fvd_statistic_is_the_frechet_distance_of_the_weighted_moments(videos, dim):
    """A resample's FVD: weighted means and unbiased weighted covariances (fewer videos than features or more)."""
    rng = np.random.default_rng(videos)
    real, fake = rng.normal(size=(videos, dim)), rng.normal(loc=0.5, size=(videos, dim))
    weights = rng.integers(0, 3, videos).astype(float)

    def moments(x):
        mean = weights @ x / weights.sum()
        return mean, ((x - mean) * weights[:, None]).T @ (x - mean) / (weights.sum() - 1.0)

    expected = frechet_distance(*moments(real), *moments(fake))
    assert fvd_statistic(real, fake)(weights) == pytest.approx(expected, rel=1e-9)


def test_fvd_slope_interval_recovers_a_growing_gap():
    rng = np.random.default_rng(5)
    clips = np.repeat(np.arange(16), 4)
    real = [rng.normal(size=(64, 4)) for _ in range(3)]
    fake = [r + shift for r, shift in zip(real, (0.0, 1.0, 2.0))]
    chunks, slope, draws = fvd_slope_interval(real, fake, clips, reps=40, seed=2)
    assert [c.estimate for c in chunks] == pytest.approx([0.0, 4.0, 16.0], abs=1e-6)
    assert slope.estimate == pytest.approx(8.0) and slope.low == pytest.approx(8.0) and len(draws) == 40
