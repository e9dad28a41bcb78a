"""Inference and training speed-ups that must not change the results: KV cache, activation checkpointing."""

from __future__ import annotations

import pytest
import torch

from orbis2.config.params import load_config
from orbis2.flow import euler_sample
from orbis2.models.sizes import stdit_config
from orbis2.models.stdit import build_stdit
from orbis2.rollout import cascaded_rollout, flat_rollout, sample_frames

from conftest import ROOT

DATA = load_config(ROOT / "params.yaml", "smoke").data
RATES = {"abstract_hz": DATA.abstract_hz, "detail_hz": DATA.detail_hz}  # the rollout's: params.yaml's data section


def _abstract(steering: bool = False, **overrides) -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_stdit(stdit_config("smoke", **overrides), latent_channels=4, causal=True, steering=steering)
    with torch.no_grad():  # a fresh model outputs zeros (adaLN-Zero): give every path non-zero weights
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model.eval()


def _detail() -> torch.nn.Module:
    torch.manual_seed(1)
    model = build_stdit("smoke", latent_channels=4, causal=False, abstract_channels=4)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model.eval()


@pytest.mark.parametrize("steering_shift", [False, True])
@pytest.mark.parametrize("n_target", [1, 3])
def test_cached_forward_equals_full_window_forward(n_target, steering_shift):
    model = _abstract(steering=True, steering_shift=steering_shift)
    context, target = torch.randn(2, 5, 4, 3, 5), torch.randn(2, n_target, 4, 3, 5)
    tau = torch.rand(2, n_target)
    steering = torch.randn(2, 5, 2)
    full = model(torch.cat([context, target], 1), torch.cat([torch.zeros(2, 5), tau], 1), frame_rate=2.0,
                 steering=steering)[:, 5:]
    cache = model.build_kv_cache(context, n_target, 2.0, steering)
    cached = model.forward_cached(target, tau, cache, 2.0, steering)
    assert full.abs().max() > 1e-3  # the comparison is not between two zero tensors
    torch.testing.assert_close(cached, full, rtol=1e-4, atol=1e-5)


def test_cache_is_refused_where_it_would_be_wrong():
    with pytest.raises(ValueError, match="causal"):
        _detail().build_kv_cache(torch.randn(1, 5, 4, 3, 5), 5)
    bidirectional = build_stdit("smoke", latent_channels=4, causal=False)
    with pytest.raises(ValueError, match="causal"):
        bidirectional.build_kv_cache(torch.randn(1, 5, 4, 3, 5), 1)


def test_sample_frames_with_cache_matches_euler_sample():
    model = _abstract()
    context = torch.randn(2, 5, 4, 3, 5)
    plain = euler_sample(model, context, 1, 6, torch.Generator().manual_seed(3), frame_rate=2.0)
    cached = sample_frames(model, context, 1, 6, torch.Generator().manual_seed(3), kv_cache=True, frame_rate=2.0)
    torch.testing.assert_close(cached, plain, rtol=1e-4, atol=1e-5)


def test_cached_and_uncached_rollouts_agree():
    top, bottom = _abstract(), _detail()
    detail_ctx, abstract_ctx = torch.randn(1, 5, 4, 3, 5), torch.randn(1, 5, 4, 3, 5)
    runs = [cascaded_rollout(top, bottom, detail_ctx, abstract_ctx, 3, torch.Generator().manual_seed(5),
                             abstract_nfe=4, detail_nfe=3, **RATES, kv_cache=cache)
            for cache in (False, True)]
    for plain, cached in zip(*runs):
        torch.testing.assert_close(cached, plain, rtol=1e-4, atol=1e-4)
    flats = [flat_rollout(top, abstract_ctx, 2, 1, 4, 2.0,
                          torch.Generator().manual_seed(6), kv_cache=cache) for cache in (False, True)]
    torch.testing.assert_close(flats[1], flats[0], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("blocks", [1, 2])
def test_checkpointed_gradients_equal_plain_gradients(blocks):
    grads = []
    for checkpointed in (0, blocks):
        model = _detail().train()
        model.checkpoint_blocks = checkpointed
        x = torch.randn(2, 10, 4, 3, 5)
        cond = torch.randn(2, 10, 4, 3, 5)
        mask = torch.zeros(2, 10, dtype=torch.bool)
        mask[:, [4, 9]] = True
        out = model(x, torch.rand(2, 10), frame_rate=10.0, cond_frames=cond, cond_mask=mask)
        (out ** 2).mean().backward()
        grads.append({name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 10
    for name in grads[0]:
        torch.testing.assert_close(grads[1][name], grads[0][name], rtol=1e-5, atol=1e-7, msg=name)


def test_gpu_policies_are_inert_on_the_cpu():
    """bf16 autocast is CUDA only: on the CPU the rollout stays fp32 and identical to the unwrapped one."""
    from orbis2.accel import Inference, inference_autocast

    assert not torch.is_autocast_enabled("cpu")
    with inference_autocast("cpu", "bf16"):
        assert not torch.is_autocast_enabled("cpu")
        y = torch.nn.Linear(4, 4)(torch.randn(2, 4))
    assert y.dtype == torch.float32
    with pytest.raises(ValueError, match="precision"):
        Inference(precision="fp16")
