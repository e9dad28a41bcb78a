"""Started by torchrun in tests/test_multinode.py: train a tiny predictor on a latent cache (every rank).

    multinode_train.py CACHE OUT [SIGNAL_AT]

With SIGNAL_AT, rank 1 sends SIGUSR1 during that step to itself and to its torchrun, as Slurm's
``--signal=USR1@<seconds>`` reaches every process of a job step; the run then stops at the next step
boundary and exits with REQUEUE_EXIT, as a stage does.
"""

import dataclasses
import os
import signal
import sys
from pathlib import Path

import torch
import torch.distributed as dist
from test_predictors import tiny_cfg

from orbis2.config.params import load_config
from orbis2.errors import REQUEUE_EXIT, TrainingStopped
from orbis2.latents import open_cache
from orbis2.tasks.predictors import PredictorTask
from orbis2.train import train

ROOT = Path(__file__).resolve().parents[1]
STEPS = 12


class SignalledPredictor(PredictorTask):
    def __init__(self, *args, at: int | None):
        super().__init__(*args)
        self.at = at

    def loss(self, model, batch, step):
        if step == self.at and dist.get_rank() == 1:
            os.kill(os.getppid(), signal.SIGUSR1)  # torchrun: it must outlive the signal
            os.kill(os.getpid(), signal.SIGUSR1)
        return super().loss(model, batch, step)


def main(cache: str, out: str, at: str | None = None) -> None:
    torch.set_num_threads(1)
    smoke = load_config(ROOT / "params.yaml", "smoke")
    cfg = tiny_cfg(smoke, "abstract_tf", context_noise_prob=0.0, context_drop_prob=0.0)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=STEPS, eval_every=0,
                                                             checkpoint_every=100))
    task = SignalledPredictor("abstract_tf", cfg, smoke.data, open_cache(Path(cache)), at=at and int(at))
    try:
        train(task, cfg.train, Path(out))
    except TrainingStopped as stop:
        print(f"rank {dist.get_rank()}: {stop}", flush=True)
        sys.exit(REQUEUE_EXIT)


if __name__ == "__main__":
    main(*sys.argv[1:])
