"""Stage `report_main` / `report_all`: the paper's tables, figures and a summary from reports/eval/.

    python stages/report.py main   # reports/main_table.csv, steering.csv, speed.csv, summary.md
    python stages/report.py all    # reports/all/: every table (ablations too), figures, summary.md
"""

import sys

from orbis2.eval.stages import run_report
from orbis2.stage import stage_main

SCOPES = ("main", "all")


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in SCOPES:
        sys.exit("usage: python stages/report.py main|all [--profile P]")
    scope = argv[0]

    def run(cfg, args, run):
        """Write the report tables, figures and summary."""
        return run_report(scope, cfg, run)

    stage_main(f"report_{scope}", ["data", "evaluation"], run, argv=argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
