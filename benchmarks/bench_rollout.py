"""Hierarchical rollout vs a flat detail-level baseline of the same size, and training-step efficiency.

    python benchmarks/bench_rollout.py [--preset default] [--steps 2] [--batch-size 8] [--threads 1]
        [--grid 9x16] [--device cpu|cuda]

Random weights at an ST-DiT preset's size, latents of 16 channels on the latent grid:

* rollout: frames per second and peak memory of (a) the cascaded model (steered
  causal abstract predictor, 15 NFE, + abstract-conditioned detail predictor,
  30 NFE) and (b) one unconditioned detail-level predictor widened until its
  parameter count matches (a)'s total (30 NFE, same 5-frame sliding window).
  Each model runs in its own subprocess so its peak memory is its own: on CUDA
  ``torch.cuda.max_memory_allocated``, on the CPU the rise of the process's peak
  RSS (``resource.getrusage``) during the rollout, which sees torch's native
  allocations that tracemalloc does not.
* training: teacher-forcing steps (forward, backward, AdamW) of each predictor;
  tokens/s and achieved FLOP/s (FLOPs counted once with
  ``torch.utils.flop_counter.FlopCounterMode``) as a fraction of this machine's
  measured fp32 matmul FLOP/s (the MFU of the paper's "25% MFU").
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from orbis2.flow import teacher_forcing_loss
from orbis2.models.stdit import STDIT_PRESETS, build_stdit
from orbis2.rollout import cascaded_rollout, flat_rollout

LATENT_CHANNELS = 16
CONTEXT, PER_STEP = 5, 5


def n_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def hierarchy(preset: str) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The steered causal abstract predictor and the abstract-conditioned detail predictor."""
    abstract = build_stdit(preset, LATENT_CHANNELS, causal=True, steering=True)
    detail = build_stdit(preset, LATENT_CHANNELS, causal=False, abstract_channels=LATENT_CHANNELS)
    return abstract, detail


def flat_baseline(preset: str) -> torch.nn.Module:
    """A detail-level predictor widened until its parameter count is closest to the whole hierarchy's."""
    with torch.device("meta"):  # sizes only, nothing allocated
        target = sum(n_params(m) for m in hierarchy(preset))
        step = 4 * STDIT_PRESETS[preset]["num_heads"]  # sin-cos positions need a multiple of 4 per head
        width = min(range(step, 8 * STDIT_PRESETS[preset]["hidden_size"], step),
                    key=lambda w: abs(n_params(build_stdit(preset, LATENT_CHANNELS, False, hidden_size=w)) - target))
    return build_stdit(preset, LATENT_CHANNELS, causal=False, hidden_size=width)


def _perturb_outputs(*models: torch.nn.Module) -> None:
    """DiT init zeroes the output layer; give it weights so sampling does real arithmetic end to end."""
    for model in models:
        torch.nn.init.normal_(model.final_layer.linear.weight, std=0.02)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def rollout_worker(args: argparse.Namespace) -> dict:
    """One model's rollout in this process: frames/s and peak memory (printed as JSON)."""
    device = torch.device(args.device)
    h, w = args.grid
    gen = torch.Generator(device=device).manual_seed(0)
    d_ctx = torch.randn(1, CONTEXT, LATENT_CHANNELS, h, w, device=device)
    if args.worker == "hierarchical":
        abstract, detail = (m.to(device).eval() for m in hierarchy(args.preset))
        _perturb_outputs(abstract, detail)
        a_ctx = torch.randn(1, CONTEXT, LATENT_CHANNELS, h, w, device=device)
        steering = torch.randn(1, args.steps, PER_STEP, 2, device=device)
        params = n_params(abstract) + n_params(detail)

        def run(steps: int) -> None:
            cascaded_rollout(abstract, detail, d_ctx, a_ctx, steps, gen, steering=steering[:, :steps])
    else:
        flat = flat_baseline(args.preset).to(device).eval()
        _perturb_outputs(flat)
        params = n_params(flat)

        def run(steps: int) -> None:
            flat_rollout(flat, d_ctx, steps, PER_STEP, 30, 10.0, gen)
    _sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # models and inputs only
    run(1)  # warm-up (kernels, allocator caches); its memory counts, its time does not
    _sync(device)
    start = time.perf_counter()
    run(args.steps)
    _sync(device)
    seconds = time.perf_counter() - start
    if device.type == "cuda":
        peak_mb = (torch.cuda.max_memory_allocated() - base) / 2**20
        total_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak_mb, total_mb = (rss_after - rss_before) / 1024, rss_after / 1024  # ru_maxrss is in KiB on Linux
    return {"params": params, "fps": PER_STEP * args.steps / seconds, "seconds": seconds,
            "peak_delta_mb": peak_mb, "peak_total_mb": total_mb}


def matmul_flops(device: torch.device, n: int = 2048, repeats: int = 5) -> float:
    """Measured fp32 matmul FLOP/s: the denominator of the achieved-FLOP/s fraction."""
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    a @ b
    _sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    _sync(device)
    return 2 * n**3 * repeats / (time.perf_counter() - start)


def train_throughput(name: str, model: torch.nn.Module, args: argparse.Namespace, device: torch.device) -> dict:
    """Teacher-forcing steps at the predictor's own window: tokens/s and FLOP/s (fp32)."""
    h, w = args.grid
    model.to(device).train()
    frames, cond = (6, {"frame_rate": 2.0, "steering": None}) if name == "abstract" else (10, {"frame_rate": 10.0})
    context = frames - 1 if name == "abstract" else CONTEXT
    b = args.batch_size
    x = torch.randn(b, frames, LATENT_CHANNELS, h, w, device=device)
    if name == "abstract":
        cond["steering"] = torch.randn(b, 5, 2, device=device)
    if name == "detail":
        mask = torch.zeros(b, frames, dtype=torch.bool, device=device)
        mask[:, [CONTEXT - 1, frames - 1]] = True
        cond.update(cond_frames=torch.randn(b, frames, LATENT_CHANNELS, h, w, device=device), cond_mask=mask)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    gen = torch.Generator(device=device).manual_seed(0)

    def step() -> None:
        loss, _ = teacher_forcing_loss(model, x[:, :context], x[:, context:], gen, **cond)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    with FlopCounterMode(display=False) as counter:
        step()  # also the warm-up
    flops = counter.get_total_flops()
    _sync(device)
    start = time.perf_counter()
    for _ in range(args.train_steps):
        step()
    _sync(device)
    seconds = (time.perf_counter() - start) / args.train_steps
    tokens = b * frames * h * w // model.patch_size**2
    return {"params": n_params(model), "tokens_per_s": tokens / seconds, "flops_per_step": flops,
            "flops_per_s": flops / seconds, "step_s": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--steps", type=int, default=2, help="rollout steps timed (0.5 s of video each)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--train-steps", type=int, default=3)
    parser.add_argument("--grid", type=lambda s: tuple(int(v) for v in s.split("x")), default=(9, 16),
                        help="latent grid HxW (default 9x16: the default profile)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (matmul peak uses the same)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--worker", choices=["hierarchical", "flat"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.worker:
        print(json.dumps(rollout_worker(args)))
        return

    argv = [sys.executable, __file__, "--preset", args.preset, "--steps", str(args.steps), "--threads",
            str(args.threads), "--device", args.device, "--grid", "x".join(map(str, args.grid))]
    rollout = {}
    for kind in ("hierarchical", "flat"):
        out = subprocess.run(argv + ["--worker", kind], check=True, capture_output=True, text=True).stdout
        rollout[kind] = json.loads(out.strip().splitlines()[-1])
    device = torch.device(args.device)
    print(f"device {args.device}, preset {args.preset}, grid {args.grid[0]}x{args.grid[1]}x{LATENT_CHANNELS}, "
          f"{args.threads} thread(s)")
    print(f"\nrollout ({args.steps} steps = {PER_STEP * args.steps} frames at 10 Hz, "
          f"peak = rise over models + inputs)")
    print(f"{'model':<14}{'params':>12}{'frames/s':>10}{'peak MB':>10}{'process MB':>12}")
    for kind, r in rollout.items():
        print(f"{kind:<14}{r['params']:>12,}{r['fps']:>10.2f}{r['peak_delta_mb']:>10.1f}"
              f"{r['peak_total_mb']:>12.1f}")
    h, f = rollout["hierarchical"], rollout["flat"]
    print(f"ratio hierarchical/flat: params {h['params'] / f['params']:.3f}, frames/s {h['fps'] / f['fps']:.2f}, "
          f"peak memory {h['peak_delta_mb'] / max(f['peak_delta_mb'], 1e-9):.2f}")

    peak = matmul_flops(device)
    print(f"\ntraining step (teacher forcing, batch {args.batch_size}, fp32), matmul peak {peak / 1e9:.1f} GFLOP/s")
    print(f"{'model':<14}{'params':>12}{'tokens/s':>12}{'GFLOP/step':>12}{'GFLOP/s':>10}{'of peak':>9}")
    models = dict(zip(("abstract", "detail"), hierarchy(args.preset)), flat=flat_baseline(args.preset))
    for name in ("abstract", "detail", "flat"):
        r = train_throughput(name, models[name], args, device)
        print(f"{name:<14}{r['params']:>12,}{r['tokens_per_s']:>12.0f}{r['flops_per_step'] / 1e9:>12.2f}"
              f"{r['flops_per_s'] / 1e9:>10.2f}{r['flops_per_s'] / peak:>9.1%}")


if __name__ == "__main__":
    main()
