"""Stage `eval_fvd_<system>`: FVD over rollouts on each evaluation split, chunked FVD and FVD-slope
-> reports/eval/fvd_<system>.json, reports/eval/media/<system>/ (sample videos, frames for the grid).

    python stages/eval_fvd.py hierarchical --profile default

Systems (``orbis2.eval.systems.SYSTEMS``): flat_detail, flat_abstract, hierarchical
(the main table), top_detail and top_abstract_10hz (hierarchy Exps. 4 and 5).
"""

import sys

from orbis2.eval.stages import run_fvd
from orbis2.eval.systems import SYSTEMS
from orbis2.stage import named_stage_main


def body(name: str):
    def run(cfg, args, run):
        """Roll out one system on the evaluation splits and measure FVD, chunked FVD and FVD-slope."""
        return run_fvd(name, cfg, run)

    return run


if __name__ == "__main__":
    named_stage_main("eval_fvd.py", "eval_fvd_", list(SYSTEMS), ["data", "assets", "evaluation"], body,
                     sys.argv[1:])
