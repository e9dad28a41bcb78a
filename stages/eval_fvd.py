"""Stage `eval_fvd_<system>`: FVD over rollouts on each evaluation split, chunked FVD and FVD-slope
-> reports/eval/fvd_<system>.json (+ sample videos, frames for the qualitative grid).

    python stages/eval_fvd.py hierarchical --profile default

Systems (``orbis2.eval.systems.SYSTEMS``): flat_detail, flat_abstract, hierarchical
(the main table), top_detail and top_abstract_10hz (hierarchy Exps. 4 and 5).
"""

import sys

from orbis2.eval.stages import run_fvd
from orbis2.eval.systems import SYSTEMS
from orbis2.stage import stage_main

SECTIONS = ["data", "assets", "evaluation"]


def main(argv: list[str]) -> None:
    if argv and argv[0].startswith("eval_fvd_"):  # the DAG passes the stage name
        argv = [argv[0][len("eval_fvd_"):], *argv[1:]]
    if not argv or argv[0] not in SYSTEMS:
        sys.exit(f"usage: python stages/eval_fvd.py <system> [--profile P]; <system> is one of {', '.join(SYSTEMS)}")
    name = argv[0]

    def run(cfg, args, run):
        """Roll out one system on the evaluation splits and measure FVD, chunked FVD and FVD-slope."""
        return run_fvd(name, cfg, run)

    stage_main(f"eval_fvd_{name}", SECTIONS, run, argv=argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
