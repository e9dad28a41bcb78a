"""Stage `abstract_df`: pre-train the abstract predictor F_H with diffusion forcing (paper eq. 2)
-> data/predictors/abstract_df/predictor.pt, reports/abstract_df.json.

Checkpoints live in data/runs/ (see `run_stage`): a killed run resumes there;
predictor.pt and the report are published atomically at the end.
"""

from orbis2.stage import stage_main
from orbis2.tasks.predictors import run_stage, stage_sections

STAGE = "abstract_df"


def run(cfg, args, run):
    """Train the predictor of this stage and publish predictor.pt with its validation loss."""
    return run_stage(STAGE, cfg, run)


if __name__ == "__main__":
    stage_main(STAGE, stage_sections(STAGE), run)
