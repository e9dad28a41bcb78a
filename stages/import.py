"""Stage `import`: bring a folder of user videos (+ optional odometry CSVs) into data/raw/import.

User videos are resampled, resized and re-encoded into the raw episode layout;
unusable ones stop the stage, or with --skip-bad (import.skip_bad) are skipped and
listed in skipped.json (path, reason, problem and fix); --strict stops at the first
whatever import.skip_bad says. With skipping, the stage fails only when no usable
train or val video is left.
"""

import json
from dataclasses import asdict
from pathlib import Path

from orbis2.data.importer import check_outside, import_videos, summary_of
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir
from orbis2.stage import open_stage, stage_parser


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["import"], __doc__)
    parser.add_argument("--videos", type=Path, default=None, help="input folder (default: import.videos)")
    parser.add_argument("--skip-bad", action="store_true", default=None,
                        help="skip unusable videos and list them in <out>/skipped.json (default: import.skip_bad)")
    parser.add_argument("--strict", dest="skip_bad", action="store_false",
                        help="stop at the first unusable video instead")
    args = parser.parse_args(argv)
    with open_stage("import", args, INTERFACES["import"]) as stage:
        cfg, run = stage.cfg, stage.run
        folder = args.videos or Path(cfg.import_.videos)
        check_outside(folder, args.out)
        skip_bad = cfg.import_.skip_bad if args.skip_bad is None else args.skip_bad

        with atomic_dir(args.out) as tmp:
            index, skipped = import_videos(folder, tmp, cfg.data, cfg.import_, skip_bad)
            (tmp / "skipped.json").write_text(json.dumps([asdict(s) for s in skipped], indent=2) + "\n")
        for s in skipped:
            print(f"[import] skipped {s.path}: {s.problem}")

        run.log_metrics({"episodes": len(index.episodes), "skipped": len(skipped)})
        stage.summary = f"{len(index.episodes)} videos imported, {summary_of(skipped)} -> {args.out}"


if __name__ == "__main__":
    main()
