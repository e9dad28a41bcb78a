"""Stage `report_main` / `report_all`: the paper's tables, figures and a summary from the evaluation records.

    python stages/report.py main   # reports/main_table.csv, steering.csv, speed.csv, summary.md, headline.json/.png
    python stages/report.py all    # reports/all/: every table (ablations too), figures, summary.md

``all`` also draws the qualitative rollout grid (from the FVD stages' saved frames)
and copies the steering strip. The pipeline's parent MLflow run gets ``main``'s
headline (at most 20 of its tables' numbers as metrics, the claims as tags, every interval as
one forest plot and one table, the tables, the stage times and ``summary.md``) and ``all``'s
figures (:mod:`orbis2.eval.report.parent`). The DAG passes every record the report reads
(``--fvd NAME=FILE``, ``--probe NAME=FILE``, ...); by hand, without them, every
record of registry.yaml's layout that exists is read.
"""

import shutil
import tempfile
from pathlib import Path

import numpy as np

from orbis2.errors import OrbisError
from orbis2.eval.figures import save_rollout_grid
from orbis2.eval.protocols.systems import SYSTEMS
from orbis2.eval.records import EVAL_KINDS
from orbis2.eval.report.claims import check_claims
from orbis2.eval.report.evals import read_evals
from orbis2.eval.report.parent import (
    FOREST_PNG,
    INTERVALS_CSV,
    STAGE_TIMES_CSV,
    intervals,
    parent_metrics,
    plot_intervals,
    write_intervals,
    write_stage_times,
)
from orbis2.eval.report.report import (
    HEADLINE_JSON,
    report_setup,
    write_full_report,
    write_main_report,
)
from orbis2.eval.report.tables import TableSettings, compression_from_evals
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, atomic_file, write_json
from orbis2.registry import layout_path, registry
from orbis2.stage import add_name_argument, open_stage, stage_parser

GRID = "grid.npz"  # the frames of the qualitative grid in an FVD stage's media folder
HEADLINE_PNG = "headline.png"  # main: the steering stage's headline figure, beside the tables


def given_or_all(given: list[tuple[str, Path]], kind: str, names: list[str], option: str) -> dict[str, Path]:
    """The ``NAME=PATH`` pairs given, else every name at its registry.yaml layout path."""
    if not given:
        return {name: layout_path(kind, name) for name in names}
    unknown = sorted(set(dict(given)) - set(names))
    if unknown:
        raise OrbisError(f"{option} {', '.join(unknown)}: unknown; known: {', '.join(names)}")
    return {name: Path(path) for name, path in given}


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["report"], __doc__)
    add_name_argument(parser, ["main", "all"], prefix="report_")
    args = parser.parse_args(argv)
    scope = args.name
    with open_stage(f"report_{scope}", args, INTERFACES["report"]) as stage:
        cfg, run = stage.cfg, stage.run
        reg = registry()
        evals = read_evals(given_or_all(args.fvd, "fvd", list(reg.systems), "--fvd"),
                           given_or_all(args.probe, "probe", reg.probe_targets, "--probe"),
                           **{kind: getattr(args, kind) for kind in EVAL_KINDS})
        setup, settings = report_setup(cfg), TableSettings.from_config(cfg)
        if scope == "main":
            out = args.out or layout_path("reports")
            written = write_main_report(evals, out, setup, settings)
            if args.headline is not None and Path(args.headline).is_file():  # the README's figure
                with atomic_file(out / HEADLINE_PNG) as tmp:
                    shutil.copyfile(args.headline, tmp)
                written.append(out / HEADLINE_PNG)
        else:
            evals.compression = compression_from_evals(evals)
            out = args.out or layout_path("report_all")
            media = given_or_all(args.media, "media", list(SYSTEMS), "--media")
            with atomic_dir(out) as tmp:
                write_full_report(evals, tmp, setup, settings)
                shutil.copy2(args.strip, tmp / "figures" / "steering_strip.png")
                grids = [(n, np.load(media[n] / GRID)) for n in SYSTEMS if n in media and (media[n] / GRID).is_file()]
                if grids:
                    times = min((g["times"] for _, g in grids), key=len)
                    save_rollout_grid([g["frames"][:len(times)] for _, g in grids],
                                      [SYSTEMS[n].label for n, _ in grids], list(times),
                                      tmp / "figures" / "rollout_grid.png")
            written = sorted(p for p in out.rglob("*") if p.is_file())
        for path in written:
            run.log_artifact(path, None if scope == "main" else "all")
        if scope == "main":  # the pipeline's parent run: the headline numbers, verdicts and summary
            # conditioning: the effect of each row (its verdict is a tag; intervals and counts stay in the CSV)
            tables = [p for p in written if p.suffix == ".csv"]
            headline_file = (args.out or layout_path("reports")) / HEADLINE_JSON
            # a one-minute read: <= 20 headline numbers, every interval as one figure and one table, the claims.
            # The same numbers under the same names are DVC's metrics (intervals and counts stay in the tables).
            numbers = parent_metrics(tables)
            write_json(headline_file, numbers)
            run.log_artifact(headline_file)
            run.publish_metrics(numbers)
            run.publish_tags({f"claim {i}": f"{verdict}: {claim}" for i, (claim, verdict, _)
                              in enumerate(check_claims(evals, settings), start=1)})
            found = intervals(tables)  # every interval as one table and one forest plot (dvc plots show's too)
            forest = plot_intervals(found, headline_file.parent / FOREST_PNG)
            table = write_intervals(found, headline_file.parent / INTERVALS_CSV)
            written += [table, forest, headline_file]
            for path in (table, forest):
                run.log_artifact(path)
            run.publish(forest, "figures")
            with tempfile.TemporaryDirectory() as tmp:  # the invocation's stage times: the parent run's only
                times = write_stage_times(run.stage_times(), Path(tmp) / STAGE_TIMES_CSV)
                for path in [*written, times]:
                    if path != forest:
                        run.publish(path, None if path.suffix == ".md" else "figures" if path.suffix == ".png"
                                    else "tables")
        else:
            for path in written:
                if path.suffix == ".png":
                    run.publish(path, "figures")
        stage.summary = f"{len(written)} files: " + ", ".join(p.name for p in written)


if __name__ == "__main__":
    main()
