"""Evaluated systems: sample placement, contexts from the cache, rollouts of every hierarchy variant."""

from pathlib import Path

import numpy as np
import pytest
import torch
from test_predictors import SPAN, C, write_cache

from orbis2.errors import OrbisError
from orbis2.eval.protocols.systems import (
    SYSTEMS,
    LoadedSystem,
    contexts_for,
    eval_samples,
    generated_indices,
    load_system,
    rollout_steps,
)
from orbis2.models.files import PredictorFile
from orbis2.models.stdit import build_stdit


def predictor(level: str, rate: str, condition: bool = False) -> PredictorFile:
    window, context = (6, 5) if rate == "slow" else (10, 5)
    model = build_stdit("smoke", C, causal=rate == "slow", abstract_channels=C if condition else None).eval()
    meta = {"level": level, "rate": rate, "frame_rate": 2.0 if rate == "slow" else 10.0,
            "window": {"window": window, "context": context}}
    return PredictorFile(model, {}, meta, "")


def test_load_system_takes_its_predictor_files_from_the_caller():
    """The stage passes the files the DAG gave it; a system's predictor without one is named."""
    with pytest.raises(OrbisError, match="'hierarchical': no predictor file given for abstract_tf"):
        load_system("hierarchical", {"detail": Path("data/predictors/detail/predictor.pt")}, {})
    with pytest.raises(OrbisError, match="no predictor file given for action"):
        load_system("hierarchical", {"detail": Path("d"), "abstract_tf": Path("a")}, {}, top_override="action")


def test_rollout_steps_and_generated_frames(smoke_cfg):
    data = smoke_cfg.data
    assert rollout_steps(data, 6.0) == 12 and rollout_steps(data, 16.0) == 32 and rollout_steps(data, 3.5) == 7
    assert generated_indices(data, 20, 2).tolist() == list(range(21, 31))


def test_eval_samples_spread_starts_and_skip_short_clips(tmp_path, smoke_cfg):
    cache = write_cache(tmp_path, {"val": [SPAN, 60, 41]})  # 26 frames: too short for 2 steps after 20 of context
    samples = eval_samples(cache, "val", smoke_cfg.data, steps=2, starts_per_clip=3)
    # clip 1 (offset 26, 60 frames): last context end 60 - 1 - 10 = 49; clip 2 (41 frames): only 20 and 30.
    assert [(s.key, s.offset, s.context_end) for s in samples] == [
        ("val-001", 26, 20), ("val-001", 26, 34), ("val-001", 26, 49),
        ("val-002", 86, 20), ("val-002", 86, 25), ("val-002", 86, 30)]
    with pytest.raises(Exception, match="long enough"):
        eval_samples(cache, "val", smoke_cfg.data, steps=10, starts_per_clip=1)


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_every_system_rolls_out_from_cache_contexts(name, tmp_path, smoke_cfg):
    torch.manual_seed(0)
    cache = write_cache(tmp_path, {"val": [60, 60]})
    specs = {"abstract_tf": ("abstract", "slow"), "detail": ("detail", "fast", True), "flat_detail": ("detail", "fast"),
             "flat_abstract": ("abstract", "fast"), "top_detail": ("detail", "slow"),
             "detail_on_detail": ("detail", "fast", True), "flat_abstract_full": ("abstract", "fast")}
    system = SYSTEMS[name]
    top = predictor(*specs[system.top]) if system.top else None
    loaded = LoadedSystem(name, system, predictor(*specs[system.bottom]), top, {})
    samples = eval_samples(cache, "val", smoke_cfg.data, steps=3, starts_per_clip=1)
    contexts = contexts_for(loaded, cache, "val", smoke_cfg.data, samples)
    assert contexts["bottom"].shape == (2, 5, C, 3, 4)
    if top is not None:
        # The top's context sits at its own rate: 2 Hz frames 0, 5, .., 20 or 10 Hz frames 16..20, same last frame.
        slow = top.meta["rate"] == "slow"
        rows = np.arange(0, 21, 5) if slow else np.arange(16, 21)
        level = top.meta["level"]
        expected = cache.arrays("val")[level][rows].astype(np.float32)  # identity normalisation
        assert torch.equal(contexts["top"][0], torch.from_numpy(expected))
    out = loaded.rollout(contexts, 3, torch.Generator().manual_seed(1), top_nfe=2, bottom_nfe=2)
    assert out.shape == (2, 15, C, 3, 4) and torch.isfinite(out).all()
    again = loaded.rollout(contexts, 3, torch.Generator().manual_seed(1), top_nfe=2, bottom_nfe=2)
    assert torch.equal(out, again)


def test_a_pair_whose_rates_do_not_fill_the_step_is_refused(tmp_path, smoke_cfg):
    """The detail frames per step follow from the rates: a top recorded at 5 Hz over a 10-Hz bottom of 5 frames
    per step would place its subgoal mid-step, so the rollout stops naming the system."""
    cache = write_cache(tmp_path, {"val": [60, 60]})
    top = predictor("abstract", "slow")
    top.meta["frame_rate"] = 5.0
    loaded = LoadedSystem("hierarchical", SYSTEMS["hierarchical"], predictor("detail", "fast", True), top, {})
    samples = eval_samples(cache, "val", smoke_cfg.data, steps=1, starts_per_clip=1)
    contexts = contexts_for(loaded, cache, "val", smoke_cfg.data, samples)
    with pytest.raises(OrbisError, match="hierarchical: the bottom predictor adds 5 frames per step, but its 10 Hz "
                                         "under a 5 Hz top gives 2"):
        loaded.rollout(contexts, 1, torch.Generator().manual_seed(1), top_nfe=1, bottom_nfe=1)
