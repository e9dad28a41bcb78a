"""Stage `latents`: both tokenizers encode every frame of data/shards once -> data/latents (fp16 memory maps)."""

from pathlib import Path

from orbis2.latents import build_latent_cache
from orbis2.stage import stage_main

SHARDS = Path("data/shards")
DETAIL = Path("data/tokenizers/detail/tokenizer.pt")
ABSTRACT = Path("data/tokenizers/abstract/tokenizer.pt")
OUT = Path("data/latents")


def run(cfg, args, run):
    """Encode every native frame of every clip with the detail and abstract tokenizers, once."""
    meta = build_latent_cache(SHARDS, OUT, DETAIL, ABSTRACT, cfg.latents.batch_size)
    frames = {split: info["frames"] for split, info in meta["splits"].items()}
    mb = sum(f.stat().st_size for f in OUT.rglob("*") if f.is_file()) / 2**20
    run.log_metrics({"frames_encoded": sum(frames.values()), "mb_written": mb,
                     **{f"{split}_frames": n for split, n in frames.items()}})
    run.log_artifact(OUT / "meta.json")
    return f"{sum(frames.values())} frames encoded {frames}, {mb:.1f} MB written -> {OUT}"


if __name__ == "__main__":
    stage_main("latents", ["data", "latents"], run)
