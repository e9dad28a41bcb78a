"""Stage `eval_speed`: generated frames per second and peak memory of the main systems
-> reports/eval/speed.json.
"""

from orbis2.eval.stages import run_speed
from orbis2.stage import stage_main


def run(cfg, args, run):
    """Time rollouts of the hierarchical and flat systems side by side in one process."""
    return run_speed(cfg, run)


if __name__ == "__main__":
    stage_main("eval_speed", ["data", "evaluation"], run)
