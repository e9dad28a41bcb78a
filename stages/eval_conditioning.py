"""Stage `eval_conditioning`: does each main predictor use its conditioning and beat trivial predictions?
-> reports/eval/conditioning.json.
"""

from pathlib import Path

from orbis2.eval.conditioning import run_conditioning
from orbis2.eval.stages import EVAL, device
from orbis2.stage import stage_main


def run(cfg, args, run):
    """Paired variant errors on val windows, one-step conditional means vs baselines, latent statistics."""
    return run_conditioning(cfg, run, device(), Path(EVAL) / "conditioning.json")


if __name__ == "__main__":
    stage_main("eval_conditioning", ["data", "evaluation"], run)
