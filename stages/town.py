"""Stage `town`: render the embedded driving world into data/raw/town (+ previews in reports/).

Every split of the procedural town: videos, odometry, depth and semantic labels,
with the motion statistics of each split and a contact sheet and preview video.
"""


from orbis2.data.town_dataset import build_town_dataset, split_motion_statistics, write_previews
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, write_json
from orbis2.stage import open_stage, stage_parser


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["town"], __doc__)
    args = parser.parse_args(argv)
    with open_stage("town", args, INTERFACES["town"]) as stage:
        cfg, run = stage.cfg, stage.run
        with atomic_dir(args.out) as tmp:
            index = build_town_dataset(tmp, cfg.data, cfg.town)
            motion = split_motion_statistics(tmp, index, cfg.town)
            write_json(tmp / "motion.json", motion)
        write_previews(args.sheet, args.preview, cfg.data, cfg.town)

        counts = {s: len(index.split(s)) for s in cfg.town.episodes}
        frames = sum(e.frames for e in index.episodes)
        run.log_metrics({"episodes": len(index.episodes), "frames": frames})
        run.log_metrics({f"motion/{split}/{k}": v for split, m in motion.items() for k, v in m.items()
                         if k in ("speed_mean", "speed_moving_mean", "stopped", "turning", "left", "right", "bend")})
        run.log_artifact(args.sheet)
        run.log_artifact(args.preview)
        train = motion["train"]
        stage.summary = (f"{len(index.episodes)} episodes {counts}, {frames} frames -> {args.out}; train: "
                         f"{train['speed_moving_mean']:.1f} m/s moving, {100 * train['turning']:.0f}% turning "
                         f"({100 * train['left']:.0f}% left, {100 * train['right']:.0f}% right), "
                         f"{100 * train['bend']:.0f}% on corner bends")


if __name__ == "__main__":
    main()
