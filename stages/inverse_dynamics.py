"""Stage `inverse_dynamics`: the learned instrument that reads speed and yaw rate from consecutive frames
-> data/inverse_dynamics/model.pt, reports/inverse_dynamics.json.
"""

from orbis2.eval.inverse_dynamics import run_inverse_dynamics
from orbis2.eval.stages import device
from orbis2.stage import stage_main


def run(cfg, args, run):
    """Train on the train split's frame pairs; val R^2 on real, reconstructed and shuffled pairs."""
    return run_inverse_dynamics(cfg, run, device())


if __name__ == "__main__":
    stage_main("inverse_dynamics", ["data", "inverse_dynamics"], run)
