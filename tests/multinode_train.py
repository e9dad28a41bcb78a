"""Started by torchrun in tests/test_multinode.py and tests/test_slurm_rehearsal.py: train a tiny predictor on a
latent cache (every rank).

    multinode_train.py CACHE OUT [SIGNAL_AT]

With SIGNAL_AT, rank 1 sends SIGUSR1 during that step to itself and to its torchrun, as Slurm's
``--signal=USR1@<seconds>`` reaches every process of a job step; the run then stops at the next step
boundary and exits with REQUEUE_EXIT, as a stage does (asking Slurm to requeue its job on SIGUSR1, inside one).
With the environment's WAIT_AT_STEP instead, every rank writes OUT.waiting.<rank> in that step and waits there
until its stop flag is up: a signal sent from outside (``scancel --signal=USR1``) then lands within the step.
"""

import dataclasses
import os
import signal
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
from test_predictors import tiny_cfg

from orbis2.config.params import load_config
from orbis2.errors import REQUEUE_EXIT, WARNING_SIGNALS, TrainingStopped
from orbis2.latents import open_cache
from orbis2.stage import requeue_slurm_job
from orbis2.tasks.predictors import PredictorTask
from orbis2.train import train

ROOT = Path(__file__).resolve().parents[1]
STEPS = 12


def rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


class SignalledPredictor(PredictorTask):
    def __init__(self, *args, at: int | None, out: Path):
        super().__init__(*args)
        self.at, self.out = at, out
        self.wait_at = int(os.environ.get("WAIT_AT_STEP", "-1"))

    def loss(self, model, batch, step):
        if step == self.at and rank() == 1:
            os.kill(os.getppid(), signal.SIGUSR1)  # torchrun: it must outlive the signal
            os.kill(os.getpid(), signal.SIGUSR1)
        if step == self.wait_at:
            self.wait_for_the_stop_flag()
        return super().loss(model, batch, step)

    def wait_for_the_stop_flag(self) -> None:
        """The training loop's handler of SIGUSR1 is a bound method of its flag holder (orbis2.train)."""
        flag = signal.getsignal(signal.SIGUSR1).__self__
        Path(self.out.parent, f"{self.out.name}.waiting.{rank()}").touch()
        deadline = time.monotonic() + 120
        while not flag.received:
            if time.monotonic() > deadline:
                raise TimeoutError("no stop signal within 120 s")
            time.sleep(0.05)


def main(cache: str, out: str, at: str | None = None) -> None:
    torch.set_num_threads(1)
    smoke = load_config(ROOT / "params.yaml", "smoke")
    cfg = tiny_cfg(smoke, "abstract_tf", context_noise_prob=0.0, context_drop_prob=0.0)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=STEPS, eval_every=0,
                                                             checkpoint_every=100))
    task = SignalledPredictor("abstract_tf", cfg, smoke.data, open_cache(Path(cache)), at=at and int(at),
                              out=Path(out))
    try:
        train(task, cfg.train, Path(out))
    except TrainingStopped as stop:
        print(f"rank {rank()}: {stop}", flush=True)
        if stop.signal_name in WARNING_SIGNALS:
            requeue_slurm_job("multinode_train")
        stop.stopped_together()
        sys.exit(REQUEUE_EXIT)


if __name__ == "__main__":
    main(*sys.argv[1:])
