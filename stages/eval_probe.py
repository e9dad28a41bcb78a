"""Stage `eval_probe_<target>`: linear probes (segmentation mIoU, depth RMSE) of one representation
-> reports/eval/probe_<target>.json.

    python stages/eval_probe.py abstract_tf --profile default

Targets: abstract_tokenizer, teacher, and every predictor stage but action
(``orbis2.eval.stages.probe_targets``).
"""

import sys

from orbis2.eval.stages import probe_targets, run_probe_stage
from orbis2.stage import named_stage_main


def body(target: str):
    def run(cfg, args, run):
        """Train linear probes on one frozen representation and score them on held-out probe frames."""
        return run_probe_stage(target, cfg, run)

    return run


if __name__ == "__main__":
    named_stage_main("eval_probe.py", "eval_probe_", probe_targets(), ["data", "evaluation"], body, sys.argv[1:])
