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

from orbis2.stage import stage_main
from orbis2.tasks.predictors import STAGES, run_stage, stage_sections


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in STAGES:
        given = repr(argv[0]) if argv else "nothing"
        sys.exit(f"usage: python stages/predictor.py <predictor> [--profile P]; <predictor> is one of "
                 f"{', '.join(STAGES)} (got {given})")
    stage = argv[0]

    def run(cfg, args, run):
        """Train one predictor and publish predictor.pt with its validation loss."""
        return run_stage(stage, cfg, run)

    stage_main(stage, stage_sections(stage), run, argv=argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
