"""Per-GPU memory of the predictor stages' training steps, estimated from params.yaml (orbis2.tasks.memory).

    python tools/train_memory.py [--profile paper] [--gpus 8] [--memory-gb 80]
        [--batch-per-gpu 4] [--checkpointing 24] [--policy selective] [--stages detail,abstract_df]

Without the overrides it checks the profile as configured; with them it answers "what if"
(e.g. a recipe for a smaller card). Exits 1 when a stage does not fit. Runs on the CPU in
seconds (the activations are calibrated on a small network).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orbis2.config.params import load_config
from orbis2.tasks.memory import stage_estimate
from orbis2.tasks.predictors import STAGES


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--gpus", type=int, default=8, help="processes the global batch is split over")
    parser.add_argument("--memory-gb", type=float, default=80.0, help="memory of one GPU")
    parser.add_argument("--batch-per-gpu", type=int, default=None, help="override: windows per GPU")
    parser.add_argument("--checkpointing", type=int, default=None, help="override: checkpointed blocks")
    parser.add_argument("--policy", choices=("full", "selective"), default=None, help="override: checkpoint policy")
    parser.add_argument("--stages", default=",".join(sorted(STAGES)))
    args = parser.parse_args(argv)
    cfg = load_config(args.params, args.profile)
    print(f"{args.profile} profile on {args.gpus} GPUs of {args.memory_gb:g} GB (GiB, bf16 autocast, DDP, EMA)")
    print(f"{'stage':<20}{'batch/GPU':>10}{'ckpt':>6}{'policy':>11}{'params':>12}{'fixed':>8}{'activ.':>8}"
          f"{'total':>8}  fits")
    missing = 0
    for stage in args.stages.split(","):
        changes = {}
        if args.batch_per_gpu is not None:
            changes["batch_size"] = args.batch_per_gpu * args.gpus
        if args.checkpointing is not None:
            changes["activation_checkpointing"] = args.checkpointing
        if args.policy is not None:
            changes["checkpoint_policy"] = args.policy
        est = stage_estimate(cfg, stage, args.gpus, **changes)
        train = cfg.section(stage).train
        ckpt = changes.get("activation_checkpointing", train.activation_checkpointing)
        policy = changes.get("checkpoint_policy", train.checkpoint_policy)
        fits = est.fits(args.memory_gb)
        missing += not fits
        print(f"{stage:<20}{est.batch:>10}{ckpt:>6}{policy:>11}{est.parameters / 1e6:>11.0f}M{est.fixed_gb:>8.1f}"
              f"{est.activations_gb:>8.1f}{est.total_gb:>8.1f}  {'yes' if fits else 'NO'}")
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
