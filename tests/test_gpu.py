"""CUDA-only checks of the GPU paths (bf16 autocast, torch.compile, SDPA kernels, checkpointing); skip on the CPU."""

from __future__ import annotations

import pytest
import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

from orbis2.accel import compile_predictor, inference_autocast, set_tf32
from orbis2.config.params import load_config
from orbis2.flow import teacher_forcing_loss
from orbis2.models.sizes import stdit_config
from orbis2.models.stdit import build_stdit
from orbis2.rollout import cascaded_rollout

from conftest import ROOT

DATA = load_config(ROOT / "params.yaml", "smoke").data
RATES = {"abstract_hz": DATA.abstract_hz, "detail_hz": DATA.detail_hz}  # the rollout's: params.yaml's data section

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
DEVICE = torch.device("cuda")
FAST_KERNELS = [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION]


def _models(preset: str = "default") -> tuple[torch.nn.Module, torch.nn.Module]:
    torch.manual_seed(0)
    top = build_stdit(preset, 16, causal=True, steering=True)
    bottom = build_stdit(preset, 16, causal=False, abstract_channels=16)
    for model in (top, bottom):
        torch.nn.init.normal_(model.final_layer.linear.weight, std=0.02)
    return top.to(DEVICE).eval(), bottom.to(DEVICE).eval()


def _rollout(top, bottom, precision: str, kv_cache: bool = True) -> torch.Tensor:
    torch.manual_seed(1)
    d_ctx, a_ctx = torch.randn(1, 5, 16, 9, 16, device=DEVICE), torch.randn(1, 5, 16, 9, 16, device=DEVICE)
    gen = torch.Generator(DEVICE).manual_seed(2)
    with inference_autocast(DEVICE, precision):
        return cascaded_rollout(top, bottom, d_ctx, a_ctx, 2, gen, abstract_nfe=4, detail_nfe=4, **RATES,
                                kv_cache=kv_cache)[0]


def test_bf16_rollout_tracks_fp32():
    set_tf32(False)
    top, bottom = _models()
    fp32, bf16 = _rollout(top, bottom, "fp32"), _rollout(top, bottom, "bf16")
    assert bf16.dtype == torch.float32 and torch.isfinite(bf16).all()
    assert (bf16 - fp32).pow(2).mean() < 0.05 * fp32.pow(2).mean()
    set_tf32(True)


def test_kv_cache_on_cuda_matches_uncached():
    top, bottom = _models()
    torch.testing.assert_close(_rollout(top, bottom, "fp32", True), _rollout(top, bottom, "fp32", False),
                               rtol=1e-3, atol=1e-3)


def test_compiled_rollout_matches_eager():
    top, bottom = _models("smoke")
    eager = _rollout(top, bottom, "bf16")
    compiled = _rollout(compile_predictor(top), compile_predictor(bottom), "bf16")
    torch.testing.assert_close(compiled, eager, rtol=5e-2, atol=5e-2)


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_attention_runs_on_flash_or_efficient_kernels(preset):
    """With the math fallback excluded, every attention call of a bf16 forward/backward must still run."""
    cfg_grid = (18, 32) if preset == "paper" else (9, 16)
    model = build_stdit(stdit_config(preset, depth=1), 16, causal=False, abstract_channels=16).to(DEVICE).train()
    x = torch.randn(1, 10, 16, *cfg_grid, device=DEVICE)
    mask = torch.zeros(1, 10, dtype=torch.bool, device=DEVICE)
    mask[:, [4, 9]] = True
    with sdpa_kernel(FAST_KERNELS), torch.autocast("cuda", dtype=torch.bfloat16):
        out = model(x, torch.rand(1, 10, device=DEVICE), 10.0, cond_frames=x, cond_mask=mask)
    out.float().pow(2).mean().backward()
    causal = build_stdit(stdit_config(preset, depth=1), 16, causal=True).to(DEVICE).eval()
    with sdpa_kernel(FAST_KERNELS), torch.autocast("cuda", dtype=torch.bfloat16), torch.no_grad():
        cache = causal.build_kv_cache(x[:, :5], 1, 2.0)
        causal.forward_cached(x[:, 5:6], torch.rand(1, 1, device=DEVICE), cache, 2.0)


def test_checkpointed_bf16_training_gradients_match():
    grads = []
    for blocks in (0, 4):
        torch.manual_seed(0)  # the same weights for both runs
        model = build_stdit("default", 16, causal=True).to(DEVICE).train()
        torch.nn.init.normal_(model.final_layer.linear.weight, std=0.02)
        model.checkpoint_blocks = blocks
        x = torch.randn(2, 6, 16, 9, 16, device=DEVICE, generator=torch.Generator(DEVICE).manual_seed(3))
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss, _ = teacher_forcing_loss(model, x[:, :5], x[:, 5:], torch.Generator(DEVICE).manual_seed(4),
                                           frame_rate=2.0)
        loss.backward()
        grads.append(torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None]))
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-2, atol=1e-4)
