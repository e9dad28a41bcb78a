"""Stage `latents`: both tokenizers encode every frame of data/shards once -> data/latents (fp16 chunks, one per shard).

    python stages/latents.py                 # detail + 16-d abstract latents -> data/latents
    python stages/latents.py latents_full    # detail + uncompressed abstract latents -> data/latents_full

The uncompressed cache (compression ablation) skips the probe split, which only
the tokenizers' probes read, from the frames.

The work is split into ``parts`` (params.yaml ``parts``, or ``--parts``), the shards' setting: part
i encodes the i-th contiguous block of each split's shards. ``--part I`` encodes that part only
(the DAG runs one job per part, Snakemake's rule ``<stage>_part``, an array of GPU jobs on
Slurm; on CUDA it decodes shards in every core of the job but one) and writes its part manifest;
without it the stage encodes every part not yet encoded,
then gathers them into ``--out``. Parts live in data/runs/ (see ``work_dir``), keyed by the
shards manifest, the tokenizers, the settings and the code: a killed part resumes at the shard
it was encoding. The latents do not depend on ``parts`` (orbis2.latents).
"""

import time

from orbis2.data.parts import add_part_options, part_name, parts_of, write_part_manifest
from orbis2.data.shards import MANIFEST, load_manifest
from orbis2.interfaces import INTERFACES
from orbis2.latents import build_latent_cache, encode_part, latent_work, load_encoders
from orbis2.registry import registry
from orbis2.stage import add_name_argument, latent_paths, open_stage, stage_parser, work_dir

# Stage name -> latent set (registry.yaml, latent_sets).
VARIANTS = {entry.stage: name for name, entry in registry().latent_sets.items()}


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["latents"], __doc__)
    add_name_argument(parser, VARIANTS, default="latents")
    add_part_options(parser, "latent_parts", prefix="<stage>/")
    args = parser.parse_args(argv)
    parts = parts_of(parser, args)
    name = args.name if args.part is None else f"{args.name}_part_{part_name(args.part, parts)}"
    with open_stage(name, args, INTERFACES["latents"]) as stage:
        cfg, run = stage.cfg, stage.run
        paths = latent_paths(args, VARIANTS[args.name])
        out = args.out or paths.root
        skip = registry().latent_sets[VARIANTS[args.name]].skip_splits
        splits = [s for s in load_manifest(args.shards)["splits"] if s not in skip]
        work = work_dir(args.name, cfg, ["data", "latents"], {"manifest": args.shards / MANIFEST, **paths.tokenizers},
                        __file__)
        settings = cfg.latents

        if args.part is not None:  # each shard is checked against the manifest just before it is read
            tokenizers, _ = load_encoders(paths.tokenizers["detail"], paths.tokenizers["abstract"])
            started = time.perf_counter()
            written = encode_part(args.shards, latent_work(work, args.shards, tokenizers, settings.batch_size, splits),
                                  tokenizers, settings.batch_size, args.part, parts, splits)
            seconds = time.perf_counter() - started
            write_part_manifest(args, "latent_parts", parts, written, prefix=f"{args.name}/")
            frames = sum(c["frames"] for chunks in written["splits"].values() for c in chunks)
            run.log_metrics({"frames": frames, "chunks": sum(map(len, written["splits"].values())),
                             "seconds": seconds})
            stage.summary = f"part {part_name(args.part, parts)}: {frames} frames ({written['encoder']}) -> {work}"
            return

        meta = build_latent_cache(args.shards, out, paths.tokenizers["detail"], paths.tokenizers["abstract"],
                                  settings.batch_size, splits, parts=parts, work=work)

        frames = {split: info["frames"] for split, info in meta["splits"].items()}
        mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
        run.log_metrics({"frames_encoded": sum(frames.values()), "mb_written": mb,
                         **{f"{split}_frames": n for split, n in frames.items()}})
        run.log_artifact(out / "meta.json")
        stage.summary = (f"{sum(frames.values())} frames encoded {frames}{f' in {parts} parts' if parts > 1 else ''}, "
                         f"{mb:.1f} MB written -> {out}")


if __name__ == "__main__":
    main()
