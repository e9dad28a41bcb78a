"""Stage `shards`: cut raw episodes into clips and write WebDataset shards + manifest to data/shards.

One WebDataset sample per clip, per split, with a manifest of counts and hashes.

The work is split into ``parts`` (params.yaml ``parts``, or ``--parts``): part i takes the i-th
contiguous block of every split's episodes. ``--part I`` writes that part only (the DAG runs one
job per part, Snakemake's rule ``shards_part``, an array of jobs on Slurm) and its part manifest;
without it the stage writes every part not yet written, then gathers them into ``--out``. Parts
live in data/runs/ (see ``work_dir``), keyed by the raw index, the settings and the code: a
killed part resumes at the shard it was writing. The samples and their order do not depend on
``parts``; where shards end does.
"""

from orbis2.data.parts import add_part_options, part_name, parts_of, write_part_manifest
from orbis2.data.shards import write_part, write_shards
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir
from orbis2.registry import layout_path
from orbis2.stage import open_stage, stage_parser, work_dir


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["shards"], __doc__)  # --raw: default the raw folder of data.source
    add_part_options(parser, "shard_parts")
    args = parser.parse_args(argv)
    parts = parts_of(parser, args)
    name = "shards" if args.part is None else f"shards_part_{part_name(args.part, parts)}"
    with open_stage(name, args, INTERFACES["shards"]) as stage:
        cfg, run = stage.cfg, stage.run
        raw = args.raw or layout_path("raw", cfg.data.source)
        work = work_dir("shards", cfg, ["data", "shards"], {"index": raw / "index.json"}, __file__)

        if args.part is not None:
            written = write_part(raw, work, cfg.data, cfg.shards, args.part, parts)
            write_part_manifest(args, "shard_parts", parts, written)
            samples = sum(s["samples"] for shards in written["splits"].values() for s in shards)
            run.log_metrics({"samples": samples})
            stage.summary = f"part {part_name(args.part, parts)}: {samples} clips -> {work}"
            return

        with atomic_dir(args.out) as tmp:
            manifest = write_shards(raw, tmp, cfg.data, cfg.shards, parts, work)

        for split, info in manifest["splits"].items():
            run.log_metrics({f"{split}_clips": info["samples"], f"{split}_shards": len(info["shards"]),
                             f"{split}_mb": sum(s["bytes"] for s in info["shards"]) / 2**20})
        run.log_artifact(args.out / "manifest.json")
        counts = {split: info["samples"] for split, info in manifest["splits"].items()}
        stage.summary = f"clips per split {counts}{f' in {parts} parts' if parts > 1 else ''} -> {args.out}"


if __name__ == "__main__":
    main()
