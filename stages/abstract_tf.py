"""Stage `abstract_tf`: fine-tune the abstract predictor F_H with teacher forcing (paper eq. 1)
-> data/predictors/abstract_tf/predictor.pt, reports/abstract_tf.json.

Checkpoints live in data/runs/ (see `run_stage`): a killed run resumes there;
predictor.pt and the report are published atomically at the end.
"""

from orbis2.stage import stage_main
from orbis2.tasks.predictors import run_stage, stage_sections

STAGE = "abstract_tf"


def run(cfg, args, run):
    """Train the predictor of this stage and publish predictor.pt with its validation loss."""
    return run_stage(STAGE, cfg, run)


if __name__ == "__main__":
    stage_main(STAGE, stage_sections(STAGE), run)
