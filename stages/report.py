"""Stage `report_main` / `report_all`: the paper's tables, figures and a summary from reports/eval/.

    python stages/report.py main   # reports/main_table.csv, steering.csv, speed.csv, summary.md
    python stages/report.py all    # reports/all/: every table (ablations too), figures, summary.md

``all`` also draws the qualitative rollout grid (from the FVD stages' saved frames)
and copies the steering strip.
"""

import shutil

import numpy as np

from orbis2.eval.report import (
    compression_from_evals,
    load_eval,
    report_setup,
    save_rollout_grid,
    write_full_report,
    write_main_report,
)
from orbis2.eval.systems import SYSTEMS
from orbis2.io import atomic_dir
from orbis2.registry import layout_path
from orbis2.stage import add_name_argument, open_stage, stage_parser

EVAL = layout_path("eval")


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser("report.py", __doc__)
    add_name_argument(parser, ["main", "all"], prefix="report_")
    args = parser.parse_args(argv)
    scope = args.name
    with open_stage(f"report_{scope}", args, ["data", "evaluation"]) as stage:
        cfg, run = stage.cfg, stage.run
        evals = load_eval(EVAL)
        setup, rates = report_setup(cfg), {"detail_hz": cfg.data.detail_hz, "abstract_hz": cfg.data.abstract_hz}
        if scope == "main":
            written = write_main_report(evals, layout_path("reports"), setup, **rates)
        else:
            evals["compression"] = compression_from_evals(evals)
            out = layout_path("report_all")
            with atomic_dir(out) as tmp:
                write_full_report(evals, tmp, setup, **rates)
                shutil.copy2(EVAL / "steering_strip.png", tmp / "figures" / "steering_strip.png")
                grids = [(n, np.load(EVAL / "media" / n / "grid.npz")) for n in SYSTEMS
                         if (EVAL / "media" / n / "grid.npz").is_file()]
                if grids:
                    times = min((g["times"] for _, g in grids), key=len)
                    save_rollout_grid([g["frames"][:len(times)] for _, g in grids],
                                      [SYSTEMS[n].label for n, _ in grids], list(times),
                                      tmp / "figures" / "rollout_grid.png")
            written = sorted(p for p in out.rglob("*") if p.is_file())
        for path in written:
            run.log_artifact(path, None if scope == "main" else "all")
        stage.summary = f"{len(written)} files: " + ", ".join(p.name for p in written)


if __name__ == "__main__":
    main()
