"""The compiled path at the depths users run it: the ``gpu`` and ``paper`` presets' ST-DiTs (depth, width and
heads), compiled by region on the CPU (inductor at the paper preset), ``fullgraph=True``, on a tiny latent grid.

What breaks at depth breaks here: a block that keeps Python state (a list it appends to, a counter) makes
dynamo compile it anew for every block and a 24-block network stops at the recompile limit. So each test
counts the unique graphs a whole run needs (the same at every depth), runs it again with
``error_on_recompile`` on (no recompile after warm-up), and compares the outputs with eager.

Outputs of inductor's CPU kernels differ from eager by float round-off (fused, reordered reductions): the
tolerances below are stated per test, a few ulps of the outputs' scale.

The compiles are shared: one model pair per preset for the module, built once (``hierarchy``).
"""

from __future__ import annotations

import copy
import math

import pytest
import torch

from orbis2.accel import RECOMPILE_LIMIT, compile_for_training, compile_predictor
from orbis2.flow import (
    diffusion_forcing_draws,
    diffusion_forcing_from_draws,
    teacher_forcing_draws,
    teacher_forcing_from_draws,
)
from orbis2.models.meta import materialize
from orbis2.models.sizes import stdit_config
from orbis2.models.stdit import build_stdit
from orbis2.rollout import cascaded_rollout
from orbis2.train import set_checkpointing

from conftest import ROOT  # noqa: F401  (the project root on sys.path for the fixtures)

# The gpu profile's predictors (params.yaml `_predictor.gpu.model`) and the paper preset.
SIZES = {"gpu": dict(hidden_size=384, depth=8, num_heads=6, cond_dim=192),
         "paper": dict(hidden_size=768, depth=24, num_heads=16, cond_dim=384)}
C = 16  # latent channels of both levels at the paper scale
GRID = (2, 3)  # a tiny latent grid: the graphs do not depend on it, the time does
RATES = {"abstract_hz": 2.0, "detail_hz": 10.0}
# A rollout's block graphs: the abstract predictor's KV-cache build and cached step, the detail step; a whole
# abstract window (no cache) is a fourth kind; the detail forward reuses the detail step's.
ROLLOUT_GRAPHS, WITH_WINDOW_GRAPHS = 3, 4


def randomized(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Every weight drawn anew, fast at 500M parameters: matrices uniform at 1/sqrt(fan-in), norm weights
    near 1, the rest small (adaLN-Zero's zeros would make every block the identity). Every parameter and buffer
    must then be finite: a tensor nothing filled after :func:`materialize` is NaN and stops the test here (its
    sum is: a NaN or infinity anywhere reaches it, without a mask as large as the tensor)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.ndim >= 2:
                p.uniform_(-1 / math.sqrt(p.shape[1]), 1 / math.sqrt(p.shape[1]), generator=gen)
            elif "norm" in name:
                p.uniform_(0.9, 1.1, generator=gen)
            else:
                p.uniform_(-0.05, 0.05, generator=gen)
    unset = [name for name, t in (*model.named_parameters(), *model.named_buffers()) if not t.sum().isfinite()]
    assert not unset, f"not initialised: {unset}"
    return model


def build(preset: str, level: str, seed: int) -> torch.nn.Module:
    """The preset's steered abstract or subgoal-conditioned detail predictor, built on the meta device and
    filled in place (the default init of 500M parameters costs tens of seconds)."""
    size = SIZES[preset]
    with torch.device("meta"):
        if level == "abstract":
            model = build_stdit(stdit_config("paper", **size, steering_shift=True), C, causal=True, steering=True)
        else:
            model = build_stdit(stdit_config("paper", **size, subgoal_shift=True), C, causal=False,
                                abstract_channels=C)
    return randomized(materialize(model, "cpu"), seed)


def inputs(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return {"detail": torch.randn(1, 5, C, *GRID, generator=gen),
            "abstract": torch.randn(1, 5, C, *GRID, generator=gen), "steering": torch.randn(1, 3, 5, 2, generator=gen)}


def rollout(top: torch.nn.Module, bottom: torch.nn.Module, x: dict[str, torch.Tensor], steps: int = 3):
    """The cascaded rollout with the KV cache on, a steered top, 2 Euler steps a level (the graphs are the same
    at 15/30)."""
    return cascaded_rollout(top, bottom, x["detail"], x["abstract"], steps, torch.Generator().manual_seed(1), 2, 2,
                            **RATES, steering=x["steering"][:, :steps], kv_cache=True)


@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    yield torch._dynamo.utils.counters
    torch._dynamo.config.error_on_recompile = False
    torch._dynamo.reset()


# The paper preset compiles with inductor (its kernels generated and run); the gpu preset's graphs are dynamo's
# alone (the ``eager`` backend): its inductor compile would add two minutes of CPU to the suite and prove
# nothing the paper preset's does not, since the graphs and their count are the same at every depth.
BACKENDS = {"gpu": "eager", "paper": "inductor"}


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["gpu", "paper"])
def test_compiled_rollout_at_gpu_and_paper_depth(preset, fresh_dynamo):
    top, bottom = build(preset, "abstract", 1).eval().requires_grad_(False), build(
        preset, "detail", 2).eval().requires_grad_(False)
    x = inputs()
    with torch.no_grad():
        eager = rollout(top, bottom, x)
        window = torch.cat([x["abstract"], eager[1][:, :1]], 1)
        tau = torch.tensor([[0.0] * 5 + [0.5]])
        eager_window = top(window, tau, 2.0, steering=x["steering"][:, 0])
        detail_window = torch.cat([x["detail"], eager[0][:, :5]], 1)
        detail_tau = torch.tensor([[0.0] * 5 + [0.5] * 5])
        cond_frames = torch.zeros(1, 10, C, *GRID)
        cond_frames[:, 4], cond_frames[:, 9] = x["abstract"][:, -1], eager[1][:, 0]
        detail_args = (detail_window, detail_tau, 10.0, cond_frames, (4, 9))
        eager_detail = bottom(*detail_args)
        compile_predictor(top, backend=BACKENDS[preset], fullgraph=True)
        compile_predictor(bottom, backend=BACKENDS[preset], fullgraph=True)
        assert torch._dynamo.config.recompile_limit >= RECOMPILE_LIMIT
        compiled = rollout(top, bottom, x)  # warm-up: compiles
        stats = fresh_dynamo["stats"]
        assert stats["unique_graphs"] == ROLLOUT_GRAPHS, dict(stats)
        compiled_window = top(window, tau, 2.0, steering=x["steering"][:, 0])  # a new kind: one more graph
        assert stats["unique_graphs"] == WITH_WINDOW_GRAPHS, dict(stats)
        compiled_detail = bottom(*detail_args)  # the detail step's graph
        assert stats["unique_graphs"] == WITH_WINDOW_GRAPHS, dict(stats)
        assert not fresh_dynamo["graph_break"], dict(fresh_dynamo["graph_break"])
        torch._dynamo.config.error_on_recompile = True  # any recompile from here on raises
        again = rollout(top, bottom, x)
        assert torch.equal(top(window, tau, 2.0, steering=x["steering"][:, 0]), compiled_window)
        torch._dynamo.config.error_on_recompile = False
    assert stats["unique_graphs"] == WITH_WINDOW_GRAPHS, dict(stats)
    for ours, reference, name in [(compiled[0], eager[0], "detail frames"), (compiled[1], eager[1], "subgoals"),
                                  (compiled_window, eager_window, "abstract window"),
                                  (compiled_detail, eager_detail, "detail forward")]:
        scale = reference.abs().max()
        assert scale > 0.1, name
        # Float round-off of fused kernels, carried through 3 rollout steps and 2 levels: 1e-4 of the scale.
        torch.testing.assert_close(ours, reference, rtol=0, atol=1e-4 * float(scale), msg=name)
    for first, second in zip(compiled, again):  # the compiled path is deterministic: the same bits again
        assert torch.equal(first, second)


def training_losses(model: torch.nn.Module, kind: str, frames: torch.Tensor, seed: int):
    """One training objective of a predictor stage, as its task computes it (``orbis2.tasks.predictors``)."""
    gen = torch.Generator().manual_seed(seed)
    if kind == "abstract_df":
        return diffusion_forcing_from_draws(model, frames[:, :6], diffusion_forcing_draws(frames[:, :6], gen),
                                            frame_rate=2.0)[0]
    if kind in ("abstract_tf", "action"):
        cond = {"frame_rate": 2.0}
        if kind == "action":
            cond["steering"] = torch.randn(frames.shape[0], 5, 2, generator=gen)
        draws = teacher_forcing_draws(frames[:, :5], frames[:, 5:6], gen)
        return teacher_forcing_from_draws(model, frames[:, :5], frames[:, 5:6], draws, **cond)[0]
    cond_frames = torch.zeros_like(frames)
    cond_frames[:, 4], cond_frames[:, 9] = frames[:, 2], frames[:, 7]
    draws = teacher_forcing_draws(frames[:, :5], frames[:, 5:], gen)
    return teacher_forcing_from_draws(model, frames[:, :5], frames[:, 5:], draws, frame_rate=10.0,
                                      cond_frames=cond_frames, cond_mask=(4, 9))[0]


@pytest.mark.slow
def test_compiled_training_step_of_each_predictor_stage_at_paper_depth(fresh_dynamo):
    """The paper profile's training set-up (``train.compile``, selective checkpointing of every block) at the
    paper preset's depth and heads: each predictor stage's loss and gradients, compiled against eager.

    Compiled through dynamo and AOTAutograd (forward and backward graphs, the checkpointing policy inside them)
    with the ``aot_eager`` backend: inductor's CPU code generation of the two backward graphs would add a
    minute to a suite that has none to spare (and is not the code a GPU runs: no profile compiles training on
    the CPU), and inductor's lowering of these blocks' forward is what the rollout test above checks.
    Width 384 instead of 768 (the gpu profile's): the paper width's weights, gradients and a second copy for
    the eager reference need 9 GB per predictor, more than the test machine lends one test; the graphs do not
    depend on the width (the rollout test above compiles the full paper preset)."""
    size = {**SIZES["paper"], "hidden_size": 384, "cond_dim": 192}
    frames = torch.randn(2, 10, C, *GRID, generator=torch.Generator().manual_seed(3))
    stages = {"abstract_df": "abstract", "abstract_tf": "abstract", "action": "abstract", "detail": "detail"}
    models = {}
    for level, seed in (("abstract", 4), ("detail", 5)):
        options = {"causal": True, "steering": True} if level == "abstract" else {"causal": False,
                                                                                 "abstract_channels": C}
        with torch.device("meta"):
            model = build_stdit(stdit_config("paper", **size), C, **options)
        models[level] = randomized(materialize(model, "cpu"), seed).train()
    graphs = {}
    for stage, level in stages.items():
        eager = copy.deepcopy(models[level])
        compiled = copy.deepcopy(models[level])
        for model in (eager, compiled):
            set_checkpointing(model, size["depth"], "selective")
        compile_for_training(compiled, backend="aot_eager", fullgraph=True)
        results = []
        for model in (eager, compiled):
            loss = training_losses(model, stage, frames if level == "detail" else frames[:, :6], seed=6)
            loss.backward()
            results.append((loss.detach(), [p.grad for p in model.parameters() if p.grad is not None]))
        (eager_loss, eager_grads), (compiled_loss, compiled_grads) = results
        torch.testing.assert_close(compiled_loss, eager_loss, rtol=1e-4, atol=0, msg=stage)
        assert len(compiled_grads) == len(eager_grads)
        for ours, reference in zip(compiled_grads, eager_grads):
            torch.testing.assert_close(ours, reference, rtol=0, atol=1e-3 * float(reference.abs().max()) + 1e-8,
                                       msg=stage)
        graphs[stage] = fresh_dynamo["stats"]["unique_graphs"]
    assert not fresh_dynamo["graph_break"], dict(fresh_dynamo["graph_break"])
    # One graph (forward and backward) for every block of the abstract stages (diffusion forcing, teacher
    # forcing and steering share it), one more for the conditioned detail blocks.
    assert graphs == {"abstract_df": 1, "abstract_tf": 1, "action": 1, "detail": 2}, graphs


def test_the_default_presets_rollout_needs_the_same_graphs():
    """Depth 4 (the default preset, 4 x 128): the same 3 graphs of a rollout as at depth 8 and 24 (dynamo's
    graphs through the ``eager`` backend: the count is the design's, whatever the backend)."""
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    size = dict(hidden_size=128, depth=4, num_heads=4, cond_dim=64)
    top = randomized(build_stdit(stdit_config("default", **size, steering_shift=True), C, causal=True,
                                 steering=True), 1).eval().requires_grad_(False)
    bottom = randomized(build_stdit(stdit_config("default", **size, subgoal_shift=True), C, causal=False,
                                    abstract_channels=C), 2).eval().requires_grad_(False)
    x = inputs()
    with torch.no_grad():
        eager = rollout(top, bottom, x)
        compile_predictor(top, backend="eager", fullgraph=True)
        compile_predictor(bottom, backend="eager", fullgraph=True)
        compiled = rollout(top, bottom, x)
        assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == ROLLOUT_GRAPHS
        torch._dynamo.config.error_on_recompile = True
        try:
            again = rollout(top, bottom, x)
        finally:
            torch._dynamo.config.error_on_recompile = False
            torch._dynamo.reset()
    for ours, second, reference in zip(compiled, again, eager):
        assert torch.equal(ours, reference) and torch.equal(second, reference)

