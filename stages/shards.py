"""Stage `shards`: cut raw episodes into clips and write WebDataset shards + manifest to data/shards.

One WebDataset sample per clip, per split, with a manifest of counts and hashes.
"""


from orbis2.data.shards import write_shards
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir
from orbis2.registry import layout_path
from orbis2.stage import open_stage, stage_parser


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["shards"], __doc__)  # --raw: default the raw folder of data.source
    args = parser.parse_args(argv)
    with open_stage("shards", args, INTERFACES["shards"]) as stage:
        cfg, run = stage.cfg, stage.run
        raw = args.raw or layout_path("raw", cfg.data.source)
        with atomic_dir(args.out) as tmp:
            manifest = write_shards(raw, tmp, cfg.data, cfg.shards)

        for split, info in manifest["splits"].items():
            run.log_metrics({f"{split}_clips": info["samples"], f"{split}_shards": len(info["shards"]),
                             f"{split}_mb": sum(s["bytes"] for s in info["shards"]) / 2**20})
        run.log_artifact(args.out / "manifest.json")
        counts = {split: info["samples"] for split, info in manifest["splits"].items()}
        stage.summary = f"clips per split {counts} -> {args.out}"


if __name__ == "__main__":
    main()
