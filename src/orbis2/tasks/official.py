"""Starting the DAG from the authors' released networks: params.yaml's ``official_weights``.

``official_weights`` names a folder written by ``orbis2 import-weights`` (:mod:`orbis2.models.official`). With it
set:

- the tokenizer stages of the main latent set (registry.yaml's ``compressed``: ``tokenizer_detail`` and
  ``tokenizer_abstract``) publish the imported tokenizers instead of training, so the latent cache, the
  predictors and the evaluation's decoders all work in the authors' latents;
- a predictor stage that models what an imported predictor models (:data:`COUNTERPARTS`: the abstract level at
  the slow rate without subgoals is their L2, the detail level at the fast rate conditioned on abstract subgoals
  their L1) is built at the architecture the import recorded (its ``build``; the stage's own steering embedder
  where the stage is steered, since theirs reads inputs ours are not) and, where its ``init_from`` is null,
  starts from the imported weights. A stage with an ``init_from`` starts from that stage as before, which then
  holds the same architecture: ``abstract_df`` fine-tunes the import with diffusion forcing and ``abstract_tf``
  continues from it; ``abstract_tf.init_from: null`` fine-tunes the import with teacher forcing directly.
  ``model`` overrides other than the steering embedder's do not apply: the architecture is the import's.

Stages without an imported counterpart (the ablations at other levels and rates, the uncompressed latents) are
unchanged. The import's rates, windows and latent grid must be the profile's; a stage refuses a mismatch with one
line naming the file. Unset (every profile's default), nothing here runs and no number moves.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orbis2.errors import OrbisError
from orbis2.models import OFFICIAL_SOURCE
from orbis2.registry import PredictorSpec, registry

if TYPE_CHECKING:  # the Snakefile reads this module's paths: it stays free of torch
    from orbis2.config.params import PipelineConfig
    from orbis2.models.files import PredictorFile

MANIFEST = "manifest.json"  # what orbis2.models.official writes beside the converted files
MAIN_LATENTS = "compressed"  # the latent set whose tokenizers the import replaces
# (level, rate, condition) of a predictor stage -> the imported predictor that models the same.
COUNTERPARTS = {("abstract", "slow", None): "predictors/abstract_tf",
                ("detail", "fast", "abstract"): "predictors/detail"}


def built_from_import(meta: dict[str, Any]) -> bool:
    """Whether a predictor file's build is an imported predictor's (the import's own file, or a stage's built
    from it): its build names every size, so no profile's preset describes it."""
    return meta.get("source") == OFFICIAL_SOURCE or "imported" in meta


def unconverted_steering(meta: dict[str, Any], path: Path) -> str | None:
    """Why an imported steered predictor cannot be steered here (its steering preprocessing was not converted,
    :func:`orbis2.models.official.converted_steering`), or None."""
    if "authors_steering" not in meta or "steering" in meta:
        return None
    name = (meta["authors_steering"].get("preprocessor") or {}).get("preprocessor", "none in its config")
    return (f"{path}: the authors' steering preprocessing ({name}) is not converted, so this predictor is not "
            f"steered here (it rolls out unconditionally); docs/official-weights.md says which is")


def _manifest(folder: str) -> dict[str, Any]:
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise OrbisError(f"params.yaml: official_weights = {folder!r} holds no {MANIFEST}; import the release "
                         f"there first (orbis2 import-weights RELEASE --out {folder})")
    return json.loads(path.read_text())


def _written(folder: str, key: str) -> Path:
    written = _manifest(folder).get("written", {})
    if key not in written:
        raise OrbisError(f"{Path(folder) / MANIFEST}: the import wrote no {key}; re-import the whole release")
    return Path(folder) / written[key]


def replaced_tokenizers() -> dict[str, str]:
    """registry.yaml tokenizer -> its level, for the tokenizers ``official_weights`` replaces."""
    return {name: level for level, name in registry().latent_sets[MAIN_LATENTS].tokenizers.items()}


def counterpart(spec: PredictorSpec) -> str | None:
    """The imported predictor (its key in the import's manifest) a stage of registry spec ``spec`` is built from."""
    return COUNTERPARTS.get((spec.level, spec.rate, spec.condition)) if spec.latents == MAIN_LATENTS else None


def imported_tokenizer(folder: str | None, tokenizer: str) -> Path | None:
    """The imported file the tokenizer stage ``tokenizer`` (a registry.yaml tokenizer) publishes, or None (unset,
    or a tokenizer outside the main latent set)."""
    level = replaced_tokenizers().get(tokenizer)
    return None if folder is None or level is None else _written(folder, f"tokenizers/{level}")


def imported_predictor(folder: str | None, spec: PredictorSpec) -> Path | None:
    """The imported predictor whose architecture a stage of registry spec ``spec`` takes, or None (unset, or no
    counterpart)."""
    key = counterpart(spec)
    return None if folder is None or key is None else _written(folder, key)


def check_tokenizer(path: Path, image_size: tuple[int, int], cfg: PipelineConfig) -> None:
    """An imported tokenizer encodes the profile's frames: its image size is ``data``'s."""
    size = (cfg.data.height, cfg.data.width)
    if tuple(image_size) != size:
        raise OrbisError(f"{path}: the authors' tokenizer encodes {image_size[0]}x{image_size[1]} frames, profile "
                         f"{cfg.profile} {size[0]}x{size[1]}; pass the profile whose data section matches the "
                         f"release")


def check_imported(predictor: PredictorFile, path: Path, cfg: PipelineConfig, level: str) -> None:
    """An imported predictor (``orbis2 import-weights``) records the rates and windows of the authors' configs;
    a rollout or a training stage at ``cfg``'s profile must use the same, or it would feed the networks inputs
    they never saw."""
    if predictor.meta.get("source") != OFFICIAL_SOURCE:
        return
    from orbis2.hierarchy import condition_slots

    d = cfg.data
    n_target = d.detail_window - d.detail_context
    expected = ({"frame_rate": d.detail_hz, "abstract_frame_rate": d.abstract_hz, "num_pred_frames": n_target,
                 "condition_slots": list(condition_slots(d.detail_context, n_target))} if level == "detail"
                else {"frame_rate": d.abstract_hz, "num_pred_frames": d.abstract_window - d.abstract_context})
    for key, value in expected.items():
        recorded = predictor.meta.get(key)
        if recorded is not None and recorded != value:
            raise OrbisError(f"{path}: the authors' config gives {key} = {recorded}, but profile {cfg.profile} uses "
                             f"{value}; pass the profile whose data section matches the release")


def stage_build(imported: PredictorFile, path: Path, spec: PredictorSpec, model: dict[str, Any],
                cfg: PipelineConfig, latent_shape: list[int]) -> dict[str, Any]:
    """The ``build`` of a stage at the imported architecture, checked against the profile and the latent cache.

    The import's build without its steering embedder (theirs reads the authors' steering inputs); a steered stage
    gets its own from the ``model`` overrides that name steering (``steering_*``).
    """
    from orbis2.hierarchy import rate_geometry

    check_imported(imported, path, cfg, spec.level)
    build = {k: v for k, v in imported.build.items() if not k.startswith("steering")}
    build["steering"] = spec.steering
    if spec.steering:
        build.update({k: v for k, v in model.items() if k.startswith("steering")})
    window = rate_geometry(cfg.data, spec.rate)[1]
    shape = [build["latent_channels"], *imported.meta["latent_grid"]]
    problems = [(build["causal"] != spec.causal, f"causal = {build['causal']}", f"{spec.causal} for the {spec.rate} "
                 f"rate"),
                (build["max_frames"] < window, f"max_frames = {build['max_frames']}", f"a {window}-frame window"),
                (shape != list(latent_shape), f"latents {shape}", f"the cache's {list(latent_shape)}")]
    for wrong, theirs, ours in problems:
        if wrong:
            raise OrbisError(f"{path}: the imported predictor has {theirs}, profile {cfg.profile} needs {ours}; "
                             f"import a release made for this profile's rates and frames (or make the latent "
                             f"cache with official_weights set)")
    return build


def start_state(imported: PredictorFile) -> dict[str, Any]:
    """The imported weights a stage starts from: without the steering embedder (see :func:`stage_build`)."""
    return {k: v for k, v in imported.model.state_dict().items() if not k.startswith("steering.")}


def publish_tokenizer(source: Path, cfg: PipelineConfig, out_file: Path, report: Path, run: Any) -> str:
    """A tokenizer stage with ``official_weights`` set: publish the imported tokenizer ``source`` as ``out_file``
    (its bytes, so the checksum the imported predictors record is the latent cache's) and a report naming it;
    returns the stage's summary line."""
    import shutil

    from orbis2.io import atomic_dir, write_json
    from orbis2.models.files import load_tokenizer

    tokenizer = load_tokenizer(source)
    check_tokenizer(source, tokenizer.model.encoder.image_size, cfg)
    with atomic_dir(out_file.parent) as tmp:
        shutil.copy2(source, tmp / out_file.name)
    write_json(report, {"imported": str(source), "checksum": tokenizer.checksum, "kind": tokenizer.kind,
                        "build": tokenizer.build})
    run.log_artifact(report)
    return f"published the imported {tokenizer.kind} tokenizer {source} (official_weights) -> {out_file}"
