"""Stage `town`: render the embedded driving world into data/raw/town (+ previews in reports/).

Every split of the procedural town: videos, odometry, depth and semantic labels,
with the motion statistics of each split and a contact sheet and preview video.

The episodes are split into ``parts`` (params.yaml ``parts``, or ``--parts``): part i renders
the i-th contiguous block of them. ``--part I`` renders that part only (the DAG runs one job
per part, Snakemake's rule ``town_part``, an array of jobs on Slurm) and writes its part
manifest; without it the stage renders every part not yet rendered, then gathers the parts
into ``--out`` with the motion statistics and previews. Parts live in data/runs/ (see
``work_dir``): a killed part loses at most the episodes it was rendering. Every episode is a
pure function of its seed, split and index: the result does not depend on ``parts``.
"""


from orbis2.data.parts import add_part_options, part_name, parts_of, write_part_manifest
from orbis2.data.town_dataset import gather_town, render_part, split_motion_statistics, write_previews
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, write_json
from orbis2.stage import open_stage, stage_parser, work_dir


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["town"], __doc__)
    add_part_options(parser, "town_parts")
    args = parser.parse_args(argv)
    parts = parts_of(parser, args)
    name = "town" if args.part is None else f"town_part_{part_name(args.part, parts)}"
    with open_stage(name, args, INTERFACES["town"]) as stage:
        cfg, run = stage.cfg, stage.run
        work = work_dir("town", cfg, ["data", "town"], {}, __file__)

        if args.part is not None:
            written = render_part(work, cfg.data, cfg.town, args.part, parts)
            write_part_manifest(args, "town_parts", parts, written)
            run.log_metrics({"episodes": len(written["records"])})
            stage.summary = f"part {part_name(args.part, parts)}: {len(written['records'])} episodes -> {work}"
            return

        written = [render_part(work, cfg.data, cfg.town, part, parts) for part in range(parts)]
        with atomic_dir(args.out) as tmp:
            index = gather_town(written, tmp, cfg.data, cfg.town)
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
        in_parts = f" in {parts} parts" if parts > 1 else ""
        stage.summary = (f"{len(index.episodes)} episodes {counts}{in_parts}, {frames} frames -> {args.out}; train: "
                         f"{train['speed_moving_mean']:.1f} m/s moving, {100 * train['turning']:.0f}% turning "
                         f"({100 * train['left']:.0f}% left, {100 * train['right']:.0f}% right), "
                         f"{100 * train['bend']:.0f}% on corner bends")


if __name__ == "__main__":
    main()
