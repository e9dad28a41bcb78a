"""Training-step efficiency of the predictors: tokens/s at every preset, MFU at the paper preset, max batch.

    python benchmarks/bench_train.py [--presets smoke,default,paper] [--mfu-preset paper] [--batch-size 4]
        [--checkpointing 24] [--policy selective] [--precision bf16] [--compile] [--max-batch 64] [--json out.json]

Random weights, 16-channel latents on the preset's latent grid (paper: 18x32),
teacher-forcing steps (forward, backward, fused AdamW on CUDA) of the abstract
predictor (6 frames at 2 Hz, causal, steered) and of the detail predictor (10
frames at 10 Hz, abstract-conditioned), with the training loop's settings:
bf16 autocast and TF32 on CUDA, per-block activation checkpointing (``--policy``
full or selective, :func:`orbis2.train.set_checkpointing`).

* **tokens/s** at every preset in ``--presets``;
* **MFU** at ``--mfu-preset``: model FLOPs per step (``FlopCounterMode``, counted
  once without checkpointing, so recomputation is not credited) per second,
  against (a) the device's dense bf16 peak from :data:`PEAK_BF16_TFLOPS` (by
  device name) and (b) a measured large bf16 matmul (fp32 on the CPU);
* **max batch** of the detail predictor with checkpointing (doubling until out
  of memory, CUDA only), with its peak memory;
* the SDPA kernels the attention shapes can use (flash / memory-efficient).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import time
from pathlib import Path

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

from orbis2.accel import compile_for_training, set_tf32
from orbis2.flow import teacher_forcing_loss
from orbis2.models.sizes import STDIT_PRESETS
from orbis2.models.stdit import build_stdit
from orbis2.train import set_checkpointing

LATENT_CHANNELS = 16
GRIDS = {"smoke": (9, 16), "default": (9, 16), "paper": (18, 32)}
# Dense (no sparsity) bf16 tensor-core peak in TFLOP/s, by a substring of torch.cuda.get_device_name().
PEAK_BF16_TFLOPS = {
    "H200": 989.0,
    "H100 SXM": 989.0,
    "H100 80GB HBM3": 989.0,  # the SXM part's usual name
    "H100 NVL": 835.0,
    "H100 PCIe": 756.0,
    "H100": 989.0,
    "GH200": 989.0,
    "B200": 2250.0,
    "A100": 312.0,
    "L40S": 362.0,
    "A10G": 70.0,
    "RTX 4090": 165.0,
}


def peak_bf16_tflops(name: str) -> float | None:
    """The table's peak for a device name (most specific key first), None if unknown."""
    for key in sorted(PEAK_BF16_TFLOPS, key=len, reverse=True):
        if key in name:
            return PEAK_BF16_TFLOPS[key]
    return None


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measured_matmul_tflops(device: torch.device, n: int = 8192, repeats: int = 20) -> float:
    """Achieved TFLOP/s of a large square matmul: bf16 on CUDA, fp32 (smaller) on the CPU."""
    if device.type != "cuda":
        n, repeats = 1024, 3
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    a, b = torch.randn(n, n, device=device, dtype=dtype), torch.randn(n, n, device=device, dtype=dtype)
    for _ in range(3):
        a @ b
    _sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    _sync(device)
    return 2 * n**3 * repeats / (time.perf_counter() - start) / 1e12


class Step:
    """One predictor's teacher-forcing training step on fixed random data."""

    def __init__(self, kind: str, preset: str, batch: int, device: torch.device, args: argparse.Namespace):
        h, w = GRIDS.get(preset, (9, 16))
        self.kind, self.device, self.batch = kind, device, batch
        with torch.device(device):  # initialise on the device: a 555M-parameter init on the CPU takes seconds
            self.model = (build_stdit(preset, LATENT_CHANNELS, causal=True, steering=True) if kind == "abstract" else
                          build_stdit(preset, LATENT_CHANNELS, causal=False, abstract_channels=LATENT_CHANNELS))
        if kind == "abstract":
            frames, self.context = 6, 5
            self.cond = {"frame_rate": 2.0, "steering": torch.randn(batch, 5, 2, device=device)}
        else:
            frames, self.context = 10, 5
            self.cond = {"frame_rate": 10.0, "cond_mask": (4, 9),  # the slots, as the training task gives them
                         "cond_frames": torch.randn(batch, frames, LATENT_CHANNELS, h, w, device=device)}
        self.model.to(device).train()
        self.checkpointing, self.policy = args.checkpointing, args.policy
        set_checkpointing(self.model, self.checkpointing, self.policy)
        torch.nn.init.normal_(self.model.final_layer.linear.weight, std=0.02)
        self.x = torch.randn(batch, frames, LATENT_CHANNELS, h, w, device=device)
        self.tokens = batch * frames * h * w
        self.forward = compile_for_training(self.model, args.backend) if args.compile else self.model  # train.compile
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=1e-4, fused=device.type == "cuda")
        self.generator = torch.Generator(device=device).manual_seed(0)
        cuda_bf16 = device.type == "cuda" and args.precision == "bf16"
        self.autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if cuda_bf16 else contextlib.nullcontext

    @property
    def params(self) -> int:
        return sum(p.numel() for p in self.model.parameters())

    def __call__(self) -> None:
        with self.autocast():
            loss, _ = teacher_forcing_loss(self.forward, self.x[:, :self.context], self.x[:, self.context:],
                                           self.generator, **self.cond)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()

    def model_flops(self) -> float:
        """FLOPs of one step as the model defines them (no recomputation), counted on a plain eager run.

        Counted on one sample and multiplied by the batch (every op is per sample), so that the run without
        checkpointing fits in memory at a batch that needs checkpointing.
        """
        set_checkpointing(self.model, 0)
        saved = self.forward, self.x, self.cond
        self.forward, self.x = self.model, self.x[:1]
        self.cond = {k: v[:1] if torch.is_tensor(v) else v for k, v in self.cond.items()}
        try:
            with FlopCounterMode(display=False) as counter:
                self()
        finally:
            set_checkpointing(self.model, self.checkpointing, self.policy)
            self.forward, self.x, self.cond = saved
        return float(counter.get_total_flops()) * self.batch

    def timed(self, steps: int, warmup: int) -> float:
        """Median seconds per step after ``warmup`` steps (compilation happens there)."""
        for _ in range(warmup):
            self()
        times = []
        for _ in range(steps):
            _sync(self.device)
            start = time.perf_counter()
            self()
            _sync(self.device)
            times.append(time.perf_counter() - start)
        return sorted(times)[len(times) // 2]


def _free(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def sdpa_backends(device: torch.device, preset: str) -> dict[str, bool]:
    """Whether flash / memory-efficient attention accept the preset's head size in bf16 (CUDA only)."""
    if device.type != "cuda":
        return {}
    cfg = STDIT_PRESETS[preset]
    head = cfg.hidden_size // cfg.num_heads
    q = torch.randn(2, cfg.num_heads, 64, head, device=device, dtype=torch.bfloat16)
    out = {}
    for name, backend in (("flash", SDPBackend.FLASH_ATTENTION), ("efficient", SDPBackend.EFFICIENT_ATTENTION)):
        try:
            with sdpa_kernel([backend]):
                torch.nn.functional.scaled_dot_product_attention(q, q, q, is_causal=True)
            out[name] = True
        except RuntimeError:
            out[name] = False
    return out


def max_batch(preset: str, device: torch.device, args: argparse.Namespace) -> dict:
    """Largest power-of-two batch of the detail predictor whose step fits in memory, with checkpointing."""
    if device.type != "cuda":
        return {"skipped": "needs CUDA"}
    best: dict = {}
    batch = 1
    while batch <= args.max_batch:
        _free(device)
        try:
            step = Step("detail", preset, batch, device, args)
            seconds = step.timed(1, 1)
            best = {"batch": batch, "peak_memory_gb": torch.cuda.max_memory_allocated(device) / 2**30,
                    "step_s": seconds, "tokens_per_s": step.tokens / seconds}
        except torch.OutOfMemoryError:
            break
        finally:
            step = None
            _free(device)
        batch *= 2
    total = torch.cuda.get_device_properties(device).total_memory / 2**30
    return {**best, "checkpointing": args.checkpointing, "policy": args.policy, "device_memory_gb": total,
            "tried_up_to": batch}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="smoke,default,paper", help="presets for tokens/s")
    parser.add_argument("--mfu-preset", default="paper")
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--checkpointing", type=int, default=0,
                        help="blocks with activation checkpointing in the timed steps (0 off)")
    parser.add_argument("--policy", choices=("full", "selective"), default="full",
                        help="what a checkpointed block keeps: its input (full) or its matmul outputs (selective)")
    parser.add_argument("--batch-checkpointing", type=int, default=1000,
                        help="blocks checkpointed in the max-batch search (default: all)")
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--backend", default="inductor",
                        help="with --compile: torch.compile's backend; aot_eager captures the forward and backward "
                             "graphs (the checkpointing policy in them) through dynamo and AOTAutograd without "
                             "generating code (tools/gpu_run.sh's CPU rehearsal: inductor's CPU code is not what runs "
                             "on a GPU)")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--max-batch", type=int, default=64, help="upper end of the max-batch search (0 skips it)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)

    def write(record: dict) -> None:  # after every run, so a run cut short still leaves what it measured
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(record, indent=2))

    set_tf32(True)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({args.threads} threads)"
    table_peak = peak_bf16_tflops(name) if device.type == "cuda" else None
    measured = measured_matmul_tflops(device)
    print(f"device {name}; bf16 peak (table) {table_peak or 'unknown'} TFLOP/s; measured matmul {measured:.1f} "
          f"TFLOP/s; {args.precision}, checkpointing {args.checkpointing}, batch {args.batch_size}")
    record: dict = {"device": name, "precision": args.precision, "compile": args.compile and args.backend,
                    "batch": args.batch_size,
                    "checkpointing": args.checkpointing, "policy": args.policy, "peak_bf16_tflops_table": table_peak,
                    "matmul_tflops_measured": measured, "sdpa": sdpa_backends(device, args.mfu_preset), "runs": []}
    print(f"{'preset':<9}{'model':<10}{'params':>14}{'tokens/s':>12}{'step s':>9}{'TFLOP/s':>9}{'MFU tbl':>9}"
          f"{'MFU mm':>8}{'peak GB':>9}")
    for preset in args.presets.split(","):
        for kind in ("abstract", "detail"):
            _free(device)
            try:
                step = Step(kind, preset, args.batch_size, device, args)
                flops = step.model_flops() if preset == args.mfu_preset else None
                seconds = step.timed(args.steps, args.warmup)
            except torch.OutOfMemoryError:
                record["runs"].append({"preset": preset, "model": kind, "error": "out of memory"})
                print(f"{preset:<9}{kind:<10}  out of memory at batch {args.batch_size}")
                continue
            run = {"preset": preset, "model": kind, "params": step.params, "tokens_per_s": step.tokens / seconds,
                   "step_s": seconds}
            if device.type == "cuda":
                run["peak_memory_gb"] = torch.cuda.max_memory_allocated(device) / 2**30
            if flops is not None:
                achieved = flops / seconds / 1e12
                run.update(flops_per_step=flops, tflops=achieved, mfu_measured_matmul=achieved / measured)
                if table_peak:
                    run["mfu"] = achieved / table_peak
            record["runs"].append(run)
            write(record)
            step = None
            fmt = (lambda key, spec, run=run: format(run[key], spec) if key in run else "-")
            print(f"{preset:<9}{kind:<10}{run['params']:>14,}{run['tokens_per_s']:>12.0f}{seconds:>9.3f}"
                  f"{fmt('tflops', '.3g'):>9}{fmt('mfu', '.1%'):>9}{fmt('mfu_measured_matmul', '.1%'):>8}"
                  f"{fmt('peak_memory_gb', '.1f'):>9}")
    if args.max_batch:
        search = argparse.Namespace(**{**vars(args), "checkpointing": args.batch_checkpointing})
        write(record)
        record["max_batch_detail"] = max_batch(args.mfu_preset, device, search)
        print(f"max batch, detail predictor at {args.mfu_preset} with checkpointing: {record['max_batch_detail']}")
    if record["sdpa"]:
        print(f"SDPA kernels usable at the {args.mfu_preset} head size: {record['sdpa']}")
    write(record)


if __name__ == "__main__":
    main()
