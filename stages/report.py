"""Stage `report_main` / `report_all`: the paper's tables, figures and a summary from reports/eval/.

    python stages/report.py main   # reports/main_table.csv, steering.csv, speed.csv, summary.md
    python stages/report.py all    # reports/all/: every table (ablations too), figures, summary.md
"""

import sys

from orbis2.eval.stages import run_report
from orbis2.stage import named_stage_main


def body(scope: str):
    def run(cfg, args, run):
        """Write the report tables, figures and summary."""
        return run_report(scope, cfg, run)

    return run


if __name__ == "__main__":
    named_stage_main("report.py", "report_", ["main", "all"], ["data", "evaluation"], body, sys.argv[1:])
