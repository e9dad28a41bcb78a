"""Stage `eval_probe_<target>`: linear probes (segmentation mIoU, depth RMSE) of one representation
-> reports/eval/probe_<target>.json.

    python stages/eval_probe.py abstract_tf --profile default

Targets: abstract_tokenizer, teacher, and every predictor stage but action
(``orbis2.eval.stages.probe_targets``).
"""

import sys

from orbis2.eval.stages import probe_targets, run_probe_stage
from orbis2.stage import stage_main

SECTIONS = ["data", "evaluation"]


def main(argv: list[str]) -> None:
    if argv and argv[0].startswith("eval_probe_"):  # the DAG passes the stage name
        argv = [argv[0][len("eval_probe_"):], *argv[1:]]
    targets = probe_targets()
    if not argv or argv[0] not in targets:
        sys.exit(f"usage: python stages/eval_probe.py <target> [--profile P]; <target> is one of {', '.join(targets)}")
    target = argv[0]

    def run(cfg, args, run):
        """Train linear probes on one frozen representation and score them on held-out probe episodes."""
        return run_probe_stage(target, cfg, run)

    stage_main(f"eval_probe_{target}", SECTIONS, run, argv=argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
