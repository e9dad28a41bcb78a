"""FVD reference rows: the real-vs-real floor, the reconstruction ceiling, the repeat-last baseline."""

import numpy as np
import pytest

from orbis2.eval.metrics.stats import paired_draws_interval
from orbis2.eval.protocols.references import fvd_with_interval, real_floor, reference_rows


def features(rng, n=64, d=6, shift=0.0):
    return rng.normal(size=(n, d)) + shift


def test_floor_halves_never_share_a_clip_and_sit_below_a_shifted_set():
    rng = np.random.default_rng(0)
    clips = np.repeat(np.arange(16), 4)
    real = features(rng)
    floor = real_floor(real, clips, splits=30, seed=1)
    shifted = fvd_with_interval(real, real + 3.0, clips, reps=50, seed=1)
    assert floor["half_splits"] == 30 and floor["clips"] == 16 and floor["videos_per_half"] == 32
    assert floor["low"] <= floor["fvd"] <= floor["high"] < shifted["low"]
    with pytest.raises(ValueError, match="at least 4 clips"):
        real_floor(real, np.repeat(np.arange(2), 32), splits=5, seed=0)
    few = reference_rows(real, real, real, np.repeat(np.arange(2), 32), reps=10, seed=0)
    assert few["real_floor"]["fvd"] is None and few["reconstruction"]["fvd"] == pytest.approx(0.0, abs=1e-9)


def test_reference_rows_order_ceiling_below_trivial_baseline():
    rng = np.random.default_rng(1)
    clips = np.repeat(np.arange(12), 4)
    real = features(rng, n=48)
    rows = reference_rows(real, real + 0.1, real * 0.0 + real.mean(axis=0) + 2.0, clips, reps=40, seed=3)
    assert set(rows) == {"real_floor", "reconstruction", "repeat_last"}
    assert rows["reconstruction"]["high"] < rows["repeat_last"]["low"]
    assert rows["reconstruction"]["fvd"] == pytest.approx(6 * 0.01, rel=1e-6)


def test_draws_with_the_same_seed_are_paired():
    """Two systems on the same clips and seed: the difference's interval is far narrower than either's."""
    rng = np.random.default_rng(2)
    clips = np.repeat(np.arange(16), 4)
    real = features(rng)
    fake = real + 1.0 + rng.normal(size=real.shape)
    a = fvd_with_interval(real, fake, clips, reps=100, seed=4)
    b = fvd_with_interval(real, fake + 0.2, clips, reps=100, seed=4)
    low, high = paired_draws_interval(b["draws"], a["draws"])
    assert 0 < low <= b["fvd"] - a["fvd"] <= high
    assert high - low < 0.5 * (a["high"] - a["low"])
