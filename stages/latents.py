"""Stage `latents`: both tokenizers encode every frame of data/shards once -> data/latents (fp16 memory maps).

    python stages/latents.py                 # detail + 16-d abstract latents -> data/latents
    python stages/latents.py latents_full    # detail + uncompressed abstract latents -> data/latents_full

The uncompressed cache (compression ablation) skips the probe split, which only
the tokenizers' probes read, from the frames.
"""


from orbis2.data.shards import load_manifest, verify_shards
from orbis2.interfaces import INTERFACES
from orbis2.latents import build_latent_cache
from orbis2.registry import registry
from orbis2.stage import add_name_argument, latent_paths, open_stage, stage_parser

# Stage name -> latent set (registry.yaml, latent_sets).
VARIANTS = {entry.stage: name for name, entry in registry().latent_sets.items()}


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["latents"], __doc__)
    add_name_argument(parser, VARIANTS, default="latents")
    args = parser.parse_args(argv)
    name = args.name
    with open_stage(name, args, INTERFACES["latents"]) as stage:
        cfg, run = stage.cfg, stage.run
        paths = latent_paths(args, VARIANTS[name])
        out = args.out or paths.root
        skip = registry().latent_sets[VARIANTS[name]].skip_splits
        splits = [s for s in load_manifest(args.shards)["splits"] if s not in skip] if skip else None
        verify_shards(args.shards, splits)  # the splits it encodes, before any read (see verify_shards)

        meta = build_latent_cache(args.shards, out, paths.tokenizers["detail"], paths.tokenizers["abstract"],
                                  cfg.latents.batch_size, splits)

        frames = {split: info["frames"] for split, info in meta["splits"].items()}
        mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
        run.log_metrics({"frames_encoded": sum(frames.values()), "mb_written": mb,
                         **{f"{split}_frames": n for split, n in frames.items()}})
        run.log_artifact(out / "meta.json")
        stage.summary = f"{sum(frames.values())} frames encoded {frames}, {mb:.1f} MB written -> {out}"


if __name__ == "__main__":
    main()
