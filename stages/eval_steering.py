"""Stage `eval_steering`: original and counterfactual steering ADE with visual odometry
-> reports/eval/steering.json, reports/eval/steering_strip.png.
"""

from orbis2.eval.stages import run_steering
from orbis2.stage import stage_main


def run(cfg, args, run):
    """Steered rollouts under five speed / yaw-rate modes, scored by scale-aligned ADE of their odometry."""
    return run_steering(cfg, run)


if __name__ == "__main__":
    stage_main("eval_steering", ["data", "town", "evaluation"], run)
