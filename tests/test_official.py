"""The authors' released networks in our files (``orbis2 import-weights``, :mod:`orbis2.models.official`).

``tests/fixtures/official/authors_tiny.pt`` holds the authors' networks at tiny sizes with random weights (their
state dicts in their key layout, inputs and outputs), made once from their code (how: ``authors_tiny.json``). A
release folder in their layout is written from it (:func:`write_release`), imported, and our networks built from
the files must reproduce their outputs within 1e-5 of the outputs' scale. ``authors_paper_shapes.json`` holds their
state dicts' keys and shapes at the paper's size: the conversion must fit our networks there too (meta device).
"""

from __future__ import annotations

import argparse
import copy
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from orbis2.cli import add_play_parser, main
from orbis2.config.params import load_config
from orbis2.data.video import read_video, write_video
from orbis2.drive import Drive, load_models, scene_of
from orbis2.errors import OrbisError
from orbis2.flow import consistency_sample, euler_sample
from orbis2.models.files import load_predictor, load_tokenizer
from orbis2.models.official import (
    ReleaseError,
    Section,
    _check_build,
    _decoder_keys,
    _tokenizer_builder,
    convert_predictor,
    convert_tokenizer,
    import_release,
    predictor_spec,
    read_checkpoint,
    tokenizer_spec,
)
from orbis2.models.stdit import build_stdit_from
from orbis2.models.stdit_layers import grid_positions
from orbis2.rollout import first_context_end, rollout_schedule, sample_frames, steering_sequences
from orbis2.tasks.official import check_imported

from conftest import ROOT

FIXTURES = Path(__file__).parent / "fixtures" / "official"
ROOT_VAR = "${oc.env:ORBIS2_MODELS_DIR}"


@pytest.fixture(scope="module")
def authors() -> dict:
    return torch.load(FIXTURES / "authors_tiny.pt", weights_only=True)


@pytest.fixture(scope="module")
def note() -> dict:
    return json.loads((FIXTURES / "authors_tiny.json").read_text())


class LightningHparams:
    """Stands for the non-tensor objects of a Lightning checkpoint: pickled by reference, so loading it would
    need this module; the importer must load the file without it."""

    def __init__(self, **values):
        self.values = values


def write_checkpoint(path: Path, state: dict[str, torch.Tensor]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": state, "hyper_parameters": LightningHparams(lr=1e-4), "epoch": 3}, path)


def predictor_checkpoint(state: dict[str, torch.Tensor], tokenizer: dict[str, torch.Tensor]) -> dict:
    """Their layout: training weights under vit.* (here perturbed: they must not be the ones converted), the EMA
    under ema_vit.*, the tokenizer's copy under ae.*."""
    out = {f"ema_vit.{k}": v for k, v in state.items()}
    out.update({f"vit.{k}": v + 0.5 for k, v in state.items()})
    out.update({f"ae.{k}": v for k, v in tokenizer.items()})
    return out


def write_release(root: Path, authors: dict, note: dict) -> Path:
    """A release folder in the authors' layout (tokenizer, L2, its distilled version, L1) from the fixture."""
    states = {name: authors[name]["state_dict"] for name in ("tokenizer", "l2", "l1")}
    return release_folder(root, note["configs"], states, pred_frames=2)


def release_folder(root: Path, cfg: dict, states: dict[str, dict[str, torch.Tensor]], pred_frames: int) -> Path:
    """A release folder in the authors' layout from their configs and state dicts; L1 predicts ``pred_frames``."""
    tok_state = dict(states["tokenizer"])
    tok_state["distill.cls_token"] = torch.zeros(1, 1, 8)  # their frozen teacher and losses: not converted
    tok_state["loss.discriminator.main.0.weight"] = torch.zeros(4, 3, 4, 4)
    write_checkpoint(root / "tokenizer" / "checkpoints" / "last.ckpt", tok_state)
    (root / "tokenizer" / "config.yaml").write_text(yaml.safe_dump({"model": cfg["tokenizer"]}))

    tokenizer_ref = {"folder": f"{ROOT_VAR}/tokenizer", "ckpt_path": None}
    module = "models.second_stage.fm_model_v2"

    def predictor_config(target, generator, sampler, branch, extra):
        params = {"tokenizer_config": tokenizer_ref, "generator_config": generator, "sampler_config": sampler,
                  "first_stage_handler_config": {"target": f"{module}.IFSelectBranchFirstStageHandler",
                                                 "params": {"encoder_branch": branch}},
                  "enc_scale": 4, "enc_scale_dino": 3.45062, "warmup_steps": 5000, **extra}
        return {"model": {"target": target, "params": params}}

    l2_sampler = {"target": "modules.fm_samplers.FlowMatchingSamplerEuler",
                  "params": {"timescale": 1000.0, "timestep_conditioning": "global"}}
    for name, target, sampler, extra in (
        ("L2", f"{module}.PredictorModule", l2_sampler, {"num_pred_frames": 1, "condition_preprocessor_config": {
            "target": "models.second_stage.fm_conditions_v2.SpeedYawDirectConditionPreprocessor",
            "params": {"steering_offsets": [5, 10, 15], "odometry_steps_per_image_frame": 5}}}),
        ("L2_distill", "models.second_stage.cd_model_v2.ConsistencyDistillPredictorModule",
         cfg["l2_distill_sampler"], {"num_pred_frames": 1, "teacher_ckpt_path": "L2/checkpoints/last.ckpt",
                                     "cd_ema_mu": 0.999}),
    ):
        folder = root / name
        write_checkpoint(folder / "checkpoints" / "last.ckpt",
                         predictor_checkpoint(states["l2"], states["tokenizer"]))
        config = predictor_config(target, cfg["l2"], sampler, "sem", extra)
        config["data"] = {"params": {"validation": {"params": {"frame_rate": 2}}}}
        (folder / "config.yaml").write_text(yaml.safe_dump(config))

    write_checkpoint(root / "L1" / "checkpoints" / "last.ckpt",
                     predictor_checkpoint(states["l1"], states["tokenizer"]))
    for file, l2 in (("config.yaml", "L2"), ("config_distill.yaml", "L2_distill")):
        preprocessor = {"target": "models.second_stage.fm_conditions_v2.L2EndpointConditionPreprocessor",
                        "params": {"l2_predictor_config": {"folder": f"{ROOT_VAR}/{l2}", "ckpt_path": None},
                                   "l2_predictor_frame_rate": 2, "l2_pred_NFE": 4 if l2 == "L2_distill" else 10,
                                   "num_context_frames": cfg["l1"]["params"]["num_context_frames"]}}
        config = predictor_config(f"{module}.L1L2PredL2PredictorModule", cfg["l1"], cfg["l1_sampler"], "rec",
                                  {"num_pred_frames": pred_frames, "condition_preprocessor_config": preprocessor,
                                   "objective_config": {"target": f"{module}.FlowMatchingObjectiveTeacherForcing"}})
        config["data"] = {"params": {"validation": {"params": {"frame_rate": 10}}}}
        (root / "L1" / file).write_text(yaml.safe_dump(config))
    return root


@pytest.fixture(scope="module")
def imported(tmp_path_factory, authors, note) -> tuple[Path, dict]:
    """The tiny release imported with their temporal mask: what reproduces their outputs."""
    root = tmp_path_factory.mktemp("official")
    release = write_release(root / "release", authors, note)
    out = root / "ours"
    return out, import_release(release, out, causal_mask="additive")


def close(ours: torch.Tensor, theirs: torch.Tensor) -> None:
    """Within 1e-5 of the reference's scale (its largest magnitude)."""
    scale = theirs.abs().max().item()
    assert scale > 1e-3, "a trivial reference proves nothing"
    error = (ours - theirs).abs().max().item()
    assert error <= 1e-5 * scale, f"max error {error:.3g} at scale {scale:.3g}"


def test_tokenizers_reproduce_the_authors_encode_and_decode(imported, authors):
    out, manifest = imported
    ref = authors["tokenizer"]
    detail = load_tokenizer(out / manifest["written"]["tokenizers/detail"])
    abstract = load_tokenizer(out / manifest["written"]["tokenizers/abstract"])
    with torch.no_grad():
        close(detail.model.encode(ref["images"]), ref["rec_latent"])
        close(abstract.model.encode(ref["images"]), ref["sem_latent"])
        close(detail.model.decoder(ref["rec_latent"]), ref["rec_decoded"])
        close(abstract.model.decoder(ref["sem_latent"]), ref["sem_decoded"])
        close(abstract.model.predict_teacher(ref["sem_latent"]), ref["sem_projection"])
    assert float(detail.scale.flatten()[0]) == 4.0 and abs(float(abstract.scale.flatten()[0]) - 3.45062) < 1e-6
    assert torch.equal(detail.model.quantizer.codebook, ref["state_dict"]["quantize.embedding.weight"])


def test_abstract_predictor_reproduces_the_authors_forward_and_consistency_sampler(imported, authors):
    out, manifest = imported
    ref, cd = authors["l2"], authors["l2_consistency"]
    standard = load_predictor(out / manifest["written"]["predictors/abstract_tf"])
    distilled = load_predictor(out / manifest["written"]["predictors/abstract_distilled"])
    model = standard.model
    b, f = ref["x"].shape[:2]
    tau = ref["t"][:, None].expand(b, f)  # global: every frame at the target's level
    with torch.no_grad():
        close(model(ref["x"], tau, frame_rate=ref["frame_rate"], steering=ref["steering"]), -ref["out"])
        close(model(ref["x"], tau, frame_rate=ref["frame_rate"]), -ref["out_all_missing"])

        def velocity(x, t):
            return distilled.model(x, t, frame_rate=ref["frame_rate"], steering=ref["steering"])

        sample = consistency_sample(velocity, cd["context"], 1, distilled.meta["sampling"]["grids"]["4"],
                                    torch.Generator(), noises=cd["noises"])
    close(sample, cd["out"])
    assert distilled.meta["sampling"]["method"] == "consistency" and standard.meta["sampling"]["method"] == "euler"
    assert standard.meta["authors_steering"]["preprocessor"]["steering_offsets"] == [5, 10, 15]
    # Their preprocessor: raw speed and yaw rate at odometry rows 5, 10, 15 after the last context frame, the
    # odometry at 2 Hz x 5 steps per frame; the distilled config names none, so it is not steered by ours.
    assert standard.meta["steering"]["offsets_s"] == [0.5, 1.0, 1.5] and standard.meta["steering"]["scale"] == [1, 1]
    assert "steering" not in distilled.meta


def test_detail_predictor_reproduces_the_authors_forward_and_euler_sampler(imported, authors):
    out, manifest = imported
    ref, eu = authors["l1"], authors["l1_euler"]
    loaded = load_predictor(out / manifest["written"]["predictors/detail"])
    slots = tuple(loaded.meta["condition_slots"])
    cond = torch.zeros(*ref["x"].shape[:2], *ref["z_l2_start"].shape[1:])
    cond[:, slots[0]], cond[:, slots[1]] = ref["z_l2_start"], ref["z_l2_end"]
    per_frame = build_stdit_from({**loaded.build, "timestep": "per_frame"})
    per_frame.load_state_dict(loaded.model.state_dict())
    with torch.no_grad():
        kwargs = {"frame_rate": ref["frame_rate"], "cond_frames": cond, "cond_mask": slots}
        close(loaded.model(ref["x"], ref["t"], **kwargs), -ref["out_global"])
        close(per_frame.eval()(ref["x"], ref["t"], **kwargs), -ref["out_per_frame"])
        sample = euler_sample(loaded.model, eu["context"], 2, eu["nfe"], torch.Generator(), noise=eu["noise"],
                              **kwargs)
    close(sample, eu["out"])


def test_our_hard_mask_is_the_default_and_hides_the_future(tmp_path, authors, note):
    """Imported without --authors-causal-mask, the abstract predictor's context no longer sees later frames (their
    mask lets it); the detail predictor (bidirectional) is the same either way."""
    out = tmp_path / "ours"
    main(["import-weights", str(write_release(tmp_path / "release", authors, note)), "--out", str(out)])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["causal_mask"] == "hard"
    model = load_predictor(out / "predictors" / "abstract_tf" / "predictor.pt").model
    ref = authors["l2"]
    x, tau = ref["x"], ref["t"][:, None].expand(ref["x"].shape[:2])
    changed = x.clone()
    changed[:, -1] += 1.0
    with torch.no_grad():
        first = model(x, tau, frame_rate=ref["frame_rate"])[:, :-1]
        assert torch.equal(first, model(changed, tau, frame_rate=ref["frame_rate"])[:, :-1])
    assert sorted(manifest["written"]) == ["predictors/abstract_distilled", "predictors/abstract_tf",
                                           "predictors/detail", "tokenizers/abstract", "tokenizers/detail"]
    assert "L1/checkpoints/last.ckpt" in manifest["files"] and manifest["training_only"]["detail"]["warmup_steps"]


@pytest.mark.parametrize("edit, message", [
    (lambda root: _edit(root / "L1" / "config.yaml", ["model", "params", "generator_config", "params",
                                                       "new_option"], 1),
     "model.params.generator_config.params.new_option is not a key this importer knows"),
    (lambda root: _edit(root / "L2" / "config.yaml", ["model", "params", "sampler_config", "params",
                                                       "integration_t_eps"], 0.01),
     "model.params.sampler_config.params.integration_t_eps = 0.01 is not supported"),
    (lambda root: (root / "tokenizer" / "checkpoints" / "last.ckpt").unlink(), "checkpoint not found"),
    (lambda root: (root / "L2_distill" / "config.yaml").unlink(), "names no folder with a config.yaml"),
])
def test_unsupported_keys_and_missing_files_are_refused_in_one_line(tmp_path, authors, note, capsys, edit, message):
    release = write_release(tmp_path / "release", authors, note)
    edit(release)
    with pytest.raises(SystemExit) as exit_info:
        main(["import-weights", str(release), "--out", str(tmp_path / "ours")])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "ours").exists()


def _edit(path: Path, keys: list[str], value) -> None:
    config = yaml.safe_load(path.read_text())
    node = config
    for key in keys[:-1]:
        node = node[key]
    node[keys[-1]] = value
    path.write_text(yaml.safe_dump(config))


def test_lightning_objects_load_as_inert_placeholders(tmp_path):
    path = tmp_path / "last.ckpt"
    write_checkpoint(path, {"vit.w": torch.ones(2)})
    with pytest.raises(pickle.UnpicklingError):  # what a plain weights_only load says about such a file
        torch.load(path, weights_only=True)
    assert torch.equal(read_checkpoint(path)["vit.w"], torch.ones(2))


def test_conversion_fits_our_networks_at_the_paper_size():
    """Their state dicts' keys and shapes at the paper's size, converted on the meta device, load strictly into
    ours; ours hold as many parameters as theirs less their fixed position table."""
    paper = json.loads((FIXTURES / "authors_paper_shapes.json").read_text())
    shapes, configs = paper["shapes"], paper["configs"]

    def meta(name):
        return {k: torch.empty(v, device="meta") for k, v in shapes[name].items()}

    sampler = {"target": "modules.fm_samplers.FlowMatchingSamplerEuler", "params": {"timescale": 1000.0}}
    for name in ("l2", "l1"):
        spec = predictor_spec(Section(Path(name), "generator_config", copy.deepcopy(configs[name])),
                              Section(Path(name), "sampler_config", copy.deepcopy(sampler)), "hard")
        state = convert_predictor(meta(name), spec, name)
        _check_build(spec.build, state, name, build_stdit_from)
        with torch.device("meta"):
            ours = sum(p.numel() for p in build_stdit_from(spec.build).parameters())
        assert ours == shapes[name + "_parameters"] - 18 * 32 * 768
    state = meta("tokenizer")
    spec = tokenizer_spec(Section(Path("tokenizer"), "model", copy.deepcopy(configs["tokenizer"])), 12, 768)
    detail, abstract, _ = convert_tokenizer(state, spec, "tokenizer")
    _check_build(spec.detail, detail, "detail", _tokenizer_builder("detail"))
    _check_build(spec.abstract, abstract, "abstract", _tokenizer_builder("abstract"))


def test_decoder_key_map_covers_every_level():
    names = _decoder_keys("decoder.", "decoder.", levels=3, blocks=2)
    assert names["decoder.up.2.attn.1."] == "decoder.up.0.3."  # lowest resolution: block, attn, block, attn
    assert names["decoder.up.2.upsample."] == "decoder.up.0.4."
    assert names["decoder.up.0.block.1."] == "decoder.up.2.1." and "decoder.up.0.upsample." not in names


def test_release_errors_are_user_errors():
    with pytest.raises(ReleaseError, match="checkpoint not found"):
        read_checkpoint(Path("/nonexistent/last.ckpt"))


def smoke_release(root: Path, note: dict) -> Path:
    """A release in the authors' layout at the smoke profile's geometry (72x128 frames, 5 + 5 detail and 5 + 1
    abstract frames): their keys and shapes there (``authors_smoke_shapes.json``), seeded random weights, their
    fixed position tables."""
    layout = json.loads((FIXTURES / "authors_smoke_shapes.json").read_text())
    generator = torch.Generator().manual_seed(0)
    states = {name: {k: torch.randn(shape, generator=generator) * 0.05 for k, shape in shapes.items()}
              for name, shapes in layout["shapes"].items()}
    for name in ("l2", "l1"):
        params = layout["configs"][name]["params"]
        (h, w), p = params["input_size"], params["patch_size"]
        states[name]["pos_embed"] = grid_positions(params["hidden_size"], h // p, w // p, torch.device("cpu"))[None]
    configs = {**layout["configs"], **{k: note["configs"][k] for k in ("l2_distill_sampler", "l1_sampler")}}
    return release_folder(root, configs, states, pred_frames=5)


class PooledPixels(torch.nn.Module):
    """A fast stand-in for I3D (the FVD's features): colour means over a coarse space-time grid."""

    def __init__(self):
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(()))  # where the features are computed

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.adaptive_avg_pool3d(video, (4, 2, 2)).flatten(1) + self.anchor


def test_an_imported_release_rolls_out_and_is_scored_with_our_commands(tmp_path, note, make_video, capsys,
                                                                       monkeypatch):
    """Imported, the release rolls out 3 s on the CPU with ``orbis2 rollout`` (Euler and, for the distilled
    abstract predictor, its consistency grid) and its rollouts are scored by ``orbis2 evaluate``."""
    release = smoke_release(tmp_path / "release", note)
    out = tmp_path / "official"
    main(["import-weights", str(release), "--out", str(out)])
    video = make_video("clip.mp4", 60, 10.0, width=128, height=72)
    files = ["--detail-tokenizer", str(out / "tokenizers" / "detail" / "tokenizer.pt"),
             "--abstract-tokenizer", str(out / "tokenizers" / "abstract" / "tokenizer.pt"),
             "--detail-predictor", str(out / "predictors" / "detail" / "predictor.pt"),
             "--profile", "smoke", "--params", str(ROOT / "params.yaml"), "--device", "cpu", "--video", str(video)]
    standard = ["--abstract-predictor", str(out / "predictors" / "abstract_tf" / "predictor.pt")]
    for seed in range(3):
        main(["rollout", *files, *standard, "--out", str(tmp_path / "generated" / f"{seed}.mp4"), "--seconds", "3",
              "--seed", str(seed)])
    rollout = read_video(tmp_path / "generated" / "0.mp4", 1, (128, 72))
    assert len(rollout) == 5 + 3 * 10 and (tmp_path / "generated" / "0.gif").is_file()
    distilled = tmp_path / "distilled.mp4"  # the consistency-distilled abstract predictor: its own 4 steps
    main(["rollout", *files, "--out", str(distilled), "--seconds", "1",
          "--abstract-predictor", str(out / "predictors" / "abstract_distilled" / "predictor.pt")])
    assert len(read_video(distilled, 1, (128, 72))) == 5 + 10
    assert "consistency-distilled: 4 steps at [0.99, 0.9375, 0.8333, 0.625]" in capsys.readouterr().err

    data = load_config(ROOT / "params.yaml", "smoke").data
    context_end = first_context_end(data)
    schedule = rollout_schedule(data, context_end, 6)
    indices = list(schedule[0].detail_context) + [i for step in schedule for i in step.detail_target]
    real = read_video(video, 1, (128, 72))[indices]
    for seed in range(3):
        write_video(tmp_path / "real" / f"{seed}.mkv", real, 10.0, lossless=True)
    monkeypatch.setattr("orbis2.eval.protocols.evaluate_videos.load_i3d", lambda path: PooledPixels())
    monkeypatch.setattr("orbis2.eval.metrics.fvd.I3D_SIZE", 32)
    (tmp_path / "i3d.pt").write_bytes(b"stand-in")
    main(["evaluate", "--generated", str(tmp_path / "generated"), "--real", str(tmp_path / "real"),
          "--context-frames", "5", "--generated-has-context", "--i3d", str(tmp_path / "i3d.pt"),
          "--params", str(ROOT / "params.yaml"), "--profile", "smoke", "--out", str(tmp_path / "record.json")])
    record = json.loads((tmp_path / "record.json").read_text())
    assert (record["pairing"]["videos"], record["fvd"]["clips"]) == (3, 3)
    assert record["fvd"]["low"] <= record["fvd"]["fvd"] <= record["fvd"]["high"] and record["fvd"]["fvd"] > 0


def test_a_rollout_step_samples_a_consistency_predictor_on_its_grid(authors):
    """``sample_frames`` with a grid is ``consistency_sample``: the same draws from the same generator."""
    net = build_stdit_from({"preset": "smoke", "latent_channels": 4, "causal": True})
    context = authors["l2"]["x"][:, :3]
    grid = [0.99, 0.8333]
    ours = sample_frames(net, context, 1, 30, torch.Generator().manual_seed(3), grid=grid, frame_rate=2.0)
    again = consistency_sample(net, context, 1, grid, torch.Generator().manual_seed(3), frame_rate=2.0)
    assert torch.equal(ours, again)


def test_a_rollout_refuses_imported_networks_whose_windows_differ_from_the_profile(imported):
    """The tiny release's detail predictor predicts 2 frames after 3; the smoke profile's rollout 5 after 5."""
    out, manifest = imported
    path = out / manifest["written"]["predictors/detail"]
    with pytest.raises(OrbisError, match="the authors' config gives num_pred_frames = 2, but profile smoke uses 5"):
        check_imported(load_predictor(path), path, load_config(ROOT / "params.yaml", "smoke"), "detail")


def test_a_heun_sampler_is_recorded_with_the_weights(tmp_path, authors, note):
    release = write_release(tmp_path / "release", authors, note)
    schedule = [{"solver": "heun", "num_steps": 2, "step_size": 0.4}, {"solver": "euler", "step_size": 0.2}]
    _edit(release / "L1" / "config.yaml", ["model", "params", "sampler_config"],
          {"target": "modules.fm_samplers.FlowMatchingSamplerHeunPlusEuler",
           "params": {"timescale": 1000.0, "step_schedule": schedule}})
    import_release(release, tmp_path / "ours")
    sampling = load_predictor(tmp_path / "ours" / "predictors" / "detail" / "predictor.pt").meta["sampling"]
    assert sampling["method"] == "heun_then_euler" and sampling["authors_sampler"]["step_schedule"] == schedule


def test_play_and_a_steered_rollout_drive_the_imported_abstract_predictor(tmp_path, note, make_video):
    """``orbis2 play``'s models and drive (what its server runs each step) on the imported release: each step feeds
    the authors' embedder speed and yaw rate at 0.5, 1 and 1.5 s after its last context frame, the command held past
    the frames driven so far; ``orbis2 rollout --trajectory`` samples the trajectory there."""
    release = smoke_release(tmp_path / "release", note)
    out = tmp_path / "official"
    main(["import-weights", str(release), "--out", str(out)])
    video = make_video("clip.mp4", 60, 10.0, width=128, height=72)
    trajectory = video.with_suffix(".csv")
    trajectory.write_text("timestamp,speed,yaw_rate\n0,4,0\n6,10,0.6\n")  # both ramp with time
    files = ["--detail-tokenizer", str(out / "tokenizers" / "detail" / "tokenizer.pt"),
             "--abstract-tokenizer", str(out / "tokenizers" / "abstract" / "tokenizer.pt"),
             "--abstract-predictor", str(out / "predictors" / "abstract_tf" / "predictor.pt"),
             "--detail-predictor", str(out / "predictors" / "detail" / "predictor.pt"),
             "--profile", "smoke", "--params", str(ROOT / "params.yaml"), "--device", "cpu"]
    parser = argparse.ArgumentParser()
    add_play_parser(parser.add_subparsers())
    models = load_models(parser.parse_args(["play", *files, "--abstract-nfe", "2", "--detail-nfe", "2"]))
    assert models.steering_offsets == [5, 10, 15]
    distilled = str(out / "predictors" / "abstract_distilled" / "predictor.pt")  # its config names no preprocessing
    with pytest.raises(OrbisError, match=r"steering preprocessing \(none in its config\) is not converted"):
        load_models(parser.parse_args(["play", *files, "--abstract-predictor", distilled]))
    drive = Drive(models, scene_of(video), seed=0)
    fed = []

    class Recording:
        def send(self, steering, stepper=drive.stepper):
            fed.append(steering)
            return stepper.send(steering)

    drive.stepper = Recording()
    frames = drive.step(7.0, 0.25)
    frames = drive.step(7.0, 0.25)
    assert frames.generated.shape == (5, 72, 128, 3) and drive.steps == 2
    last = drive.context_end  # the first step's last context frame: recorded before it, commanded after
    assert torch.equal(fed[0], torch.tensor([[[7.0, 0.25]] * 3]))
    assert len(drive.speed) == last + 11 and float(drive.speed[last]) == 4 + 6 * last / 60

    main(["rollout", *files, "--video", str(video), "--trajectory", str(trajectory), "--seconds", "1",
          "--out", str(tmp_path / "steered.mp4")])
    assert len(read_video(tmp_path / "steered.mp4", 1, (128, 72))) == 5 + 10
    schedule = rollout_schedule(load_config(ROOT / "params.yaml", "smoke").data, last, 2)
    speed = 4 + np.arange(80) / 60 * 6
    steering = steering_sequences(schedule, speed, speed / 10 - 0.4, [1.0, 1.0], models.steering_offsets)
    rows = [[last + o for o in (5, 10, 15)], [last + 5 + o for o in (5, 10, 15)]]
    assert torch.allclose(steering[..., 0], torch.tensor(speed[rows], dtype=torch.float32))
