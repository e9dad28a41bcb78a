"""Stage `<predictor>`: train one predictor of the hierarchy or of its ablations
-> data/predictors/<predictor>/predictor.pt, reports/<predictor>.json.

    python stages/predictor.py abstract_df --profile default

The predictor names are the keys of ``orbis2.tasks.predictors.STAGES`` (each
with its params.yaml section of the same name): abstract_df, abstract_tf,
detail, action, and the ablations abstract_tf_only, flat_detail,
flat_abstract, top_detail, detail_on_detail. Checkpoints live in data/runs/
(see ``run_stage``): a killed run resumes there; predictor.pt and the report
are published atomically at the end.
"""

import sys

from orbis2.stage import named_stage_main
from orbis2.tasks.predictors import STAGES, run_stage, stage_sections


def body(stage: str):
    def run(cfg, args, run):
        """Train one predictor and publish predictor.pt with its validation loss."""
        return run_stage(stage, cfg, run)

    return run


if __name__ == "__main__":
    stage = sys.argv[1] if len(sys.argv) > 1 else ""
    named_stage_main("predictor.py", "", list(STAGES), stage_sections(stage), body, sys.argv[1:])
