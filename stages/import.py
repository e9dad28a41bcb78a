"""Stage `import`: bring a folder of user videos (+ optional odometry CSVs) into data/raw/import.

User videos are resampled, resized and re-encoded into the raw episode layout;
unusable ones stop the stage, or with --skip-bad (import.skip_bad) are skipped and
listed in skipped.json (path, reason, problem and fix); --strict stops at the first
whatever import.skip_bad says. With skipping, the stage fails only when no usable
train or val video is left.

The videos are split into ``parts`` (params.yaml ``parts``, or ``--parts``): part i takes
the i-th contiguous block of them. ``--part I`` imports that part only (the DAG runs one job
per part, Snakemake's rule ``import_part``) and writes its part manifest; without it the stage
imports every video not yet imported, then gathers the parts into ``--out``. Parts live in
data/runs/ (see ``work_dir``); a video already imported from the same file (size and time) is
not read again, so a killed part loses at most the video it was importing.
"""

import json
from dataclasses import asdict
from pathlib import Path

from orbis2.data.importer import check_outside, gather_import, import_part, summary_of
from orbis2.data.parts import add_part_options, part_name, parts_of, write_part_manifest
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir
from orbis2.stage import open_stage, stage_parser, work_dir


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["import"], __doc__)
    parser.add_argument("--videos", type=Path, default=None, help="input folder (default: import.videos)")
    parser.add_argument("--skip-bad", action="store_true", default=None,
                        help="skip unusable videos and list them in <out>/skipped.json (default: import.skip_bad)")
    parser.add_argument("--strict", dest="skip_bad", action="store_false",
                        help="stop at the first unusable video instead")
    add_part_options(parser, "import_parts")
    args = parser.parse_args(argv)
    parts = parts_of(parser, args)
    name = "import" if args.part is None else f"import_part_{part_name(args.part, parts)}"
    with open_stage(name, args, INTERFACES["import"]) as stage:
        cfg, run = stage.cfg, stage.run
        folder = args.videos or Path(cfg.import_.videos)
        check_outside(folder, args.out)
        skip_bad = cfg.import_.skip_bad if args.skip_bad is None else args.skip_bad
        work = work_dir("import", cfg, ["data", "import"], {}, __file__)

        if args.part is not None:
            written = import_part(folder, work, cfg.data, cfg.import_, skip_bad, args.part, parts)
            write_part_manifest(args, "import_parts", parts, written)
            imported = sum("record" in o for o in written["outcomes"])
            run.log_metrics({"episodes": imported})
            stage.summary = (f"part {part_name(args.part, parts)}: {imported} of {len(written['outcomes'])} videos "
                             f"imported -> {work}")
            return

        written = [import_part(folder, work, cfg.data, cfg.import_, skip_bad, part, parts) for part in range(parts)]
        with atomic_dir(args.out) as tmp:
            index, skipped = gather_import(folder, written, tmp, cfg.data)
            (tmp / "skipped.json").write_text(json.dumps([asdict(s) for s in skipped], indent=2) + "\n")
        for s in skipped:
            print(f"[import] skipped {s.path}: {s.problem}")

        run.log_metrics({"episodes": len(index.episodes), "skipped": len(skipped)})
        in_parts = f" in {parts} parts" if parts > 1 else ""
        stage.summary = f"{len(index.episodes)} videos imported{in_parts}, {summary_of(skipped)} -> {args.out}"


if __name__ == "__main__":
    main()
