"""What ``orbis2 evaluate`` does, for the command and the DAG's ``evaluate_<name>`` rule alike.

:func:`evaluate_videos` loads I3D (and the steering instrument when the rollouts
have trajectories) and scores the pairs through :func:`orbis2.eval.protocols.evaluate.evaluate_pairs`,
the code of the ``eval_fvd`` stages. :func:`read_rollout_folder` reads a folder of
``data/rollouts/<name>/`` (a manifest, or generated/ and real/, plus the options
file that stands in for the command's options), and :func:`plot_record` draws a
record's FVDs with their intervals beside its reference rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml

from orbis2.assets import AssetError, ensure_asset
from orbis2.eval.evaluate_records import EvaluateRecord
from orbis2.eval.figures import pyplot, save_figure
from orbis2.eval.metrics.odometry import get_inverse_dynamics
from orbis2.eval.protocols.evaluate import (
    EvaluateError,
    Pair,
    context_frames,
    evaluate_pairs,
    pairs_from_folders,
    pairs_from_manifest,
    protocol,
    reference_rows,
)
from orbis2.eval.protocols.evaluate_steering import add_steering
from orbis2.io import sha256_file
from orbis2.models.i3d import load_i3d

MANIFEST = "manifest.csv"
OPTIONS_FILE = "evaluate.yaml"
# The options file's keys: the `orbis2 evaluate` options of the same names, with their defaults.
OPTIONS = {"context_frames": None, "generated_has_context": False, "protocol": "orbis2", "instrument": "learned",
           "hfov_deg": None, "split": "videos"}


@dataclass(frozen=True)
class RolloutFolder:
    """A folder of rollouts as the ``evaluate_<name>`` rule reads it: the pairs and the options file's values."""

    folder: Path
    pairs: list[Pair]
    options: dict[str, Any]

    @property
    def manifest(self) -> Path | None:
        return self.folder / MANIFEST if (self.folder / MANIFEST).is_file() else None

    def files(self) -> list[Path]:
        """Every file the score depends on: the folder's own files, and what a manifest names outside it."""
        inside = {f for f in self.folder.rglob("*") if f.is_file()}
        named = {f for p in self.pairs for f in (p.generated, p.real, p.trajectory) if f is not None}
        return sorted(inside | named)


def read_rollout_folder(folder: Path) -> RolloutFolder:
    """``folder/manifest.csv`` (columns as ``--manifest``), else ``folder/generated/`` and ``folder/real/`` matched by
    file name; ``folder/evaluate.yaml`` optionally sets :data:`OPTIONS` (e.g. ``context_frames: 3``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EvaluateError(f"{folder}: no such folder; put the rollouts there ({MANIFEST}, or generated/ and real/)")
    options = dict(OPTIONS)
    options_file = folder / OPTIONS_FILE
    if options_file.is_file():
        given = yaml.safe_load(options_file.read_text()) or {}
        if not isinstance(given, dict):
            raise EvaluateError(f"{options_file}: expected a mapping of options ({', '.join(OPTIONS)})")
        unknown = sorted(set(given) - set(OPTIONS))
        if unknown:
            raise EvaluateError(f"{options_file}: unknown option(s) {unknown}; it may set {', '.join(OPTIONS)}")
        options.update(given)
    if (folder / MANIFEST).is_file():
        pairs = pairs_from_manifest(folder / MANIFEST)
    elif (folder / "generated").is_dir() and (folder / "real").is_dir():
        pairs = pairs_from_folders(folder / "generated", folder / "real")
    else:
        raise EvaluateError(f"{folder}: holds neither {MANIFEST} nor the folders generated/ and real/; put the "
                            f"rollouts there as `orbis2 evaluate` takes them (docs/evaluate.md)")
    return RolloutFolder(folder, pairs, options)


def i3d_file(given: Path | None, cfg, assets: Path | None = None) -> Path:
    """The I3D weights: ``given``, else those the ``assets`` stage put in ``assets`` (default ``assets.dir``)."""
    if given is not None:
        if not Path(given).is_file():
            raise EvaluateError(f"{given}: I3D weights not found; pass the converted i3d_kinetics400.pt")
        return Path(given)
    try:
        return ensure_asset("i3d_kinetics400", Path(assets or cfg.assets.dir), cfg.assets.local.get("i3d_kinetics400"),
                            download=False)
    except AssetError as err:
        raise EvaluateError(f"{err}; or pass converted weights with --i3d") from err


def evaluate_videos(pairs: list[Pair], cfg, *, context: int | None = None, where: Path | None = None,
                    protocol_name: str = "orbis2", generated_has_context: bool = False, split: str = "videos",
                    i3d: Path | None = None, assets: Path | None = None, instrument: str = "learned",
                    instrument_weights: Path | None = None, hfov_deg: float | None = None,
                    device: str | None = None) -> EvaluateRecord:
    """The record of ``orbis2 evaluate``: FVD, chunked FVD, references, warnings and card of ``pairs`` under the
    protocol named for ``cfg``'s evaluation section; steering scores too when the rollouts have trajectories.
    ``where`` (the manifest) is named when the context length is missing; I3D is ``i3d``, else the assets'."""
    proto = protocol(protocol_name, cfg.evaluation)
    weights = i3d_file(i3d, cfg, assets)
    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    network = load_i3d(weights).to(dev).eval()
    stated = context_frames(pairs, context, where)
    reader = get_inverse_dynamics(instrument, instrument_weights) if any(p.trajectory for p in pairs) else None
    record = evaluate_pairs(pairs, stated, proto, network, sha256_file(weights), generated_has_context, split)
    if reader is not None:
        record = add_steering(record, pairs, proto, generated_has_context, reader, instrument,
                              hfov_deg if hfov_deg is not None else cfg.town.hfov_deg)
    return record


def plot_record(record: EvaluateRecord, path: Path) -> None:
    """FVD over the protocol's window and over each chunk, with their bootstrap intervals, against the end of the
    window (s); the reference rows as horizontal lines."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    fvd, card = record.fvd, record.protocol
    ax.errorbar([fvd.seconds], [fvd.fvd], yerr=[[fvd.fvd - fvd.low], [fvd.high - fvd.fvd]],
                fmt="s", capsize=4, label=f"FVD (0-{fvd.seconds:g} s)")
    if record.chunked is not None:
        chunks = record.chunked.chunks
        ax.errorbar([c.end_s for c in chunks], [c.fvd for c in chunks],
                    yerr=[[c.fvd - c.low for c in chunks], [c.high - c.fvd for c in chunks]],
                    fmt="o-", capsize=4, label=f"chunked FVD ({record.chunked.chunk_seconds:g}-s windows)")
    for (name, row), style in zip(reference_rows(record), ("--", ":", "-.")):
        if row.fvd is not None:
            ax.axhline(row.fvd, linestyle=style, color="grey", label=name)
    ax.set_xlabel("end of window (s after the context)")
    ax.set_ylabel("FVD")
    ax.set_title(f"protocol {card.protocol}: {card.videos} videos, {card.clips} clips, "
                 f"{card.context_frames} context frames", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path)
