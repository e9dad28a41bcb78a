"""Stage `evaluate_<name>`: score a folder of any model's rollouts, as `orbis2 evaluate` does
-> reports/evaluate/<name>/fvd.json (the record), table.txt (the table and its protocol card), fvd.png.

    snakemake --cores 2 reports/evaluate/<name>/fvd.json      # reads data/rollouts/<name>/
    python stages/evaluate.py --rollouts data/rollouts/<name>

The folder holds manifest.csv, or generated/ and real/ matched by file name, and
optionally evaluate.yaml with the options `orbis2 evaluate` would take
(``context_frames``, ``generated_has_context``, ``protocol``, ``instrument``,
``hfov_deg``, ``split``; :mod:`orbis2.eval.protocols.evaluate_videos`). A rule with a
wildcard, so Snakemake only: dvc.yaml's stages are fixed.
"""

from pathlib import Path

from orbis2.eval.metrics.inverse_dynamics import WEIGHTS_FILE
from orbis2.eval.protocols.evaluate import format_table, reference_rows
from orbis2.eval.protocols.evaluate_videos import evaluate_videos, plot_record, read_rollout_folder
from orbis2.eval.records import write_record
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_file
from orbis2.stage import open_stage, stage_parser

INTERFACE = INTERFACES["evaluate"]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)  # --assets: I3D; <name>: the rollout folder's
    parser.add_argument("--i3d", type=Path, default=None, help="I3D weights (default: the assets' i3d_kinetics400.pt)")
    args = parser.parse_args(argv)
    name = args.rollouts.name
    out = {key: getattr(args, key) or INTERFACE.option(key).path(name) for key in ("fvd", "table", "figure")}
    with open_stage(f"evaluate_{name}", args, INTERFACE) as stage:
        cfg, run = stage.cfg, stage.run
        folder = read_rollout_folder(args.rollouts)
        opts = folder.options
        record = evaluate_videos(folder.pairs, cfg, context=opts["context_frames"], where=folder.manifest,
                                 protocol_name=opts["protocol"], generated_has_context=opts["generated_has_context"],
                                 split=opts["split"], i3d=args.i3d, assets=args.assets,
                                 instrument=opts["instrument"],
                                 instrument_weights=args.instrument / WEIGHTS_FILE, hfov_deg=opts["hfov_deg"])
        table = format_table(record)
        write_record(out["fvd"], record)
        with atomic_file(out["table"]) as tmp:
            tmp.write_text(table + "\n")
        plot_record(record, out["figure"])
        for file in out.values():
            run.log_artifact(file)
        fvd = record.fvd
        run.log_params({"rollout_videos": fvd.videos, "rollout_clips": fvd.clips, "protocol": opts["protocol"]})
        run.log_metrics({"fvd": fvd.fvd, "fvd_low": fvd.low, "fvd_high": fvd.high})
        run.log_metrics({f"fvd_{ref}": row.fvd for ref, row in reference_rows(record) if row.fvd is not None})
        if record.chunked is not None:
            run.log_metrics({"fvd_slope": record.chunked.fvd_slope})
        if record.steering is not None:
            run.log_metrics({"steering_ade_m": record.steering.ade_m.estimate,
                             "steering_turn_deg": record.steering.turn_deg.estimate})
        stage.summary = f"{name}: " + table.splitlines()[0]


if __name__ == "__main__":
    main()
