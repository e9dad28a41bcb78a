"""ST-DiT predictor: causality, per-frame noise levels, initialisation, conditioning, presets, overfitting."""

from __future__ import annotations

import math

import pytest
import torch

from orbis2.errors import OrbisError
from orbis2.flow import teacher_forcing_loss
from orbis2.models import full_build
from orbis2.models.deviations import SteeringShift, SubgoalShift, translate_columns
from orbis2.models.files import load_predictor, save_predictor
from orbis2.models.sizes import STDIT_PRESETS, STDiTConfig, stdit_config
from orbis2.models.stdit import build_stdit, build_stdit_from
from orbis2.models.stdit_layers import SteeringEmbedder, patchify, unpatchify

C, H, W = 4, 3, 5  # latent channels and a small latent grid for the fast tests


def n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def latents(b: int, f: int, seed: int, c: int = C, h: int = H, w: int = W) -> torch.Tensor:
    return torch.randn(b, f, c, h, w, generator=torch.Generator().manual_seed(seed))


def randomized(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Give the zero-initialised parameters (adaLN, final layer, biases) random values, so outputs are non-trivial."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            if not p.any():
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    return model


def detail_inputs(b: int, f: int, seed: int, c_a: int = 3, grid=(H, W)):
    cond = latents(b, f, seed, c_a, *grid)
    mask = torch.zeros(b, f, dtype=torch.bool)
    mask[:, [f // 2 - 1, f - 1]] = True  # the last context frame and the last predicted frame
    return {"cond_frames": cond * mask[:, :, None, None, None], "cond_mask": mask}


@pytest.mark.parametrize("causal", [True, False])
def test_causal_temporal_attention_hides_the_future(causal):
    torch.manual_seed(0)
    model = randomized(build_stdit("smoke", C, causal=causal)).eval()
    x, tau = latents(2, 5, 1), torch.rand(2, 5)
    changed_x, changed_tau = x.clone(), tau.clone()
    changed_x[:, 3] += 1.0
    changed_tau[:, 4] = 0.9
    with torch.no_grad():
        out = model(x, tau, frame_rate=2.0)
        out_changed = model(changed_x, changed_tau, frame_rate=2.0)
    past = (out[:, :3] - out_changed[:, :3]).abs().max().item()
    assert (out[:, 3:] - out_changed[:, 3:]).abs().max() > 1e-3
    if causal:
        assert past < 1e-6
    else:
        assert past > 1e-3


def test_noise_level_is_embedded_per_frame():
    torch.manual_seed(0)
    model = randomized(build_stdit("smoke", C, causal=True)).eval()
    x, tau = latents(2, 4, 1), torch.full((2, 4), 0.5)
    changed = tau.clone()
    changed[:, 2] = 0.1
    with torch.no_grad():
        out, out_changed = model(x, tau), model(x, changed)
        single = [model(x[:, :1], torch.full((2, 1), t)) for t in (0.0, 1.0)]
    assert torch.equal(out[:, :2], out_changed[:, :2])  # causal: earlier frames do not see it
    assert (out[:, 2] - out_changed[:, 2]).abs().max() > 1e-3
    assert (single[0] - single[1]).abs().max() > 1e-3  # one frame, no temporal mixing: tau still acts
    with pytest.raises(ValueError, match="one noise level per frame"):
        model(x, torch.rand(2))


def test_fresh_model_outputs_zero_and_conditioning_paths_learn():
    torch.manual_seed(0)
    model = build_stdit("smoke", C, causal=False, abstract_channels=3)
    x, tau, cond = latents(2, 6, 1), torch.rand(2, 6), detail_inputs(2, 6, 2)
    out = model(x, tau, **cond)
    assert out.shape == x.shape and torch.count_nonzero(out) == 0
    for block in model.blocks:  # gates of the abstract paths are small but open
        gate = torch.sigmoid(block.cond_modulation[-1].bias[2 * model.hidden_size :])
        assert torch.all((gate > 0.05) & (gate < 0.3))
        assert torch.all(torch.tanh(block.cross_gate) > 0.05)

    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    target = latents(2, 6, 3)
    for _ in range(2):
        optimizer.zero_grad()
        ((model(x, tau, **cond) - target) ** 2).mean().backward()
        optimizer.step()
    grads = {name: p.grad for name, p in model.named_parameters()}
    for name in ("abstract.patchify.weight", "abstract.frame_position.0.weight",
                 "blocks.0.cond_modulation.1.weight", "blocks.0.cross_attn.kv.weight", "blocks.0.cross_gate"):
        assert grads[name].abs().sum() > 0, name
    with torch.no_grad():
        other = {**cond, "cond_frames": cond["cond_frames"] + detail_inputs(2, 6, 4)["cond_frames"]}
        assert (model(x, tau, **cond) - model(x, tau, **other)).abs().max() > 0


def test_steering_embedder_missing_values_and_dropout():
    torch.manual_seed(0)
    embedder = SteeringEmbedder(hidden_size=16, num_features=2, max_len=8)
    torch.nn.init.normal_(embedder.no_value)
    torch.nn.init.normal_(embedder.position)
    torch.nn.init.normal_(embedder.out.weight, std=0.3)
    torch.nn.init.normal_(embedder.null)
    steering = torch.randn(3, 5, 2)
    steering[0] = float("nan")
    steering[1, :, 0] = float("nan")
    tokens = embedder.tokens(steering)
    torch.testing.assert_close(tokens[0], embedder.no_value.sum(0) + embedder.position[:5])
    yaw_only = embedder.feature_mlps[1](steering[1, :, 1:])
    torch.testing.assert_close(tokens[1], embedder.no_value[0] + yaw_only + embedder.position[:5])
    assert torch.isfinite(tokens).all()

    drop = torch.tensor([False, True, False])
    emb = embedder(steering, drop)
    assert torch.equal(emb[1], embedder.null.detach()) and not torch.equal(emb[0], emb[1])
    assert (embedder(steering.flip(1))[2] - emb[2]).abs().max() > 1e-4  # the order of the sequence matters

    fresh = SteeringEmbedder(16, 2, 8)
    assert torch.count_nonzero(fresh(steering)) == 0  # a new embedder leaves the predictor unchanged


def test_steered_model_uses_the_null_path_without_steering():
    torch.manual_seed(0)
    model = randomized(build_stdit("smoke", C, causal=True, steering=True)).eval()
    x, tau = latents(2, 3, 1), torch.rand(2, 3)
    steering = torch.randn(2, 5, 2)
    with torch.no_grad():
        unsteered = model(x, tau)
        dropped = model(x, tau, steering=steering, steering_drop=torch.tensor([True, True]))
        steered = model(x, tau, steering=steering)
    assert torch.equal(unsteered, dropped)
    assert (steered - unsteered).abs().max() > 1e-4
    with pytest.raises(ValueError, match="without steering"):
        build_stdit("smoke", C, causal=True)(x, tau, steering=steering)


def test_translate_columns_moves_content_sideways():
    x = torch.arange(2 * 3 * 4, dtype=torch.float32).reshape(2, 1, 3, 4) + 1
    moved = translate_columns(x, torch.tensor([1.0, -0.5]))
    assert torch.equal(moved[0, :, :, 1:], x[0, :, :, :-1])  # content at column j lands on j + 1
    assert (moved[0, :, :, 0] == 0).all()  # zero (the dataset mean) enters from the border
    torch.testing.assert_close(moved[1, :, :, :-1], (x[1, :, :, :-1] + x[1, :, :, 1:]) / 2)
    torch.testing.assert_close(translate_columns(x, torch.zeros(2)), x)


def test_steering_shift_starts_silent_follows_the_yaw_rate_and_learns_to_predict_the_turn():
    torch.manual_seed(0)
    shift = SteeringShift(C, 16, patch_size=1)
    previous, steering = torch.randn(3, C, H, W), torch.randn(3, 5, 2)
    assert torch.count_nonzero(shift(previous, steering)) == 0  # the steered model starts as the pre-trained one
    negated = steering * torch.tensor([1.0, -1.0])
    torch.testing.assert_close(shift.columns(negated, W), -shift.columns(steering, W))
    torch.testing.assert_close(shift.columns(steering, 2 * W), 2 * shift.columns(steering, W))  # grid widths
    with torch.no_grad():
        shift.embed.weight.normal_()
    drop = torch.tensor([False, True, False])
    assert (shift(previous, steering, drop)[1] == 0).all() and shift(previous, steering, drop)[0].abs().sum() > 0

    # Known answer: the next frame is the previous one moved sideways in proportion to the yaw rate.
    # From a silent start, the embedding learns to predict it, and then depends on the yaw rate's sign.
    shift.reset_parameters()
    readout = torch.nn.Linear(16, C)
    optimizer = torch.optim.Adam([*shift.parameters(), *readout.parameters()], lr=0.02)
    smooth = torch.sin(torch.linspace(0, 3, W) + torch.randn(64, C, H, 1))  # varies across columns
    yaw = (torch.rand(64) * 2 - 1) * 4
    target = translate_columns(smooth, yaw * W / 16)
    steer = torch.stack([torch.zeros(64), yaw], 1)[:, None].expand(64, 5, 2)

    def error(steering: torch.Tensor) -> torch.Tensor:
        prediction = readout(shift(smooth, steering)).transpose(1, 2).reshape(64, C, H, W)
        return (prediction - target)[..., 1:-1].pow(2).mean()

    for _ in range(300):
        optimizer.zero_grad()
        loss = error(steer)
        loss.backward()
        optimizer.step()
    baseline = (smooth - target)[..., 1:-1].pow(2).mean()  # repeat the previous frame
    assert error(steer) < 0.05 * baseline
    assert error(steer * torch.tensor([1.0, -1.0])) > 0.5 * baseline


def test_subgoal_shift_moves_the_last_context_frame_by_the_subgoals_motion():
    torch.manual_seed(0)
    shift = SubgoalShift(C, 16, patch_size=1)
    b, f, w_a = 3, 6, 16  # slots: 3 context frames (the last conditioned), 3 predicted (the last conditioned)
    x = torch.sin(torch.linspace(0, 6, 2 * W) + torch.randn(b, f, C, H, 1))  # a grid twice the width of W
    base = torch.sin(torch.linspace(0, 6, w_a) + torch.randn(b, 2, H, 1))
    moved = torch.tensor([2.0, -1.5, 0.0])  # abstract columns
    cond = torch.zeros(b, f, 2, H, w_a)
    cond[:, 2], cond[:, 5] = base, translate_columns(base, moved)
    mask = torch.zeros(b, f, dtype=torch.bool)
    mask[:, [2, 5]] = True
    first, tokens = shift(x, cond, mask)
    assert first == 2 and tokens.shape == (b, 3, H * 2 * W, 16)
    assert torch.count_nonzero(tokens) == 0  # zero-initialised: the predictor starts as the plain one

    # Known answer: with an identity embedding, predicted frame k of 3 sees the last context frame moved
    # by k/3 of the subgoal's shift, scaled from the 16-column abstract grid to the 10-column one.
    identity = SubgoalShift(C, C, patch_size=1)
    with torch.no_grad():
        identity.embed.weight.copy_(torch.eye(C))
    _, tokens = identity(x, cond, mask)
    for k in range(1, 4):
        expected = translate_columns(x[:, 2], moved * (2 * W / w_a) * k / 3)
        torch.testing.assert_close(tokens[:, k - 1], patchify(expected[:, None], 1)[:, 0])
    assert identity(x, cond, mask.logical_and(torch.arange(f) < 5)) is None  # one conditioned slot: no input


def test_subgoal_shift_needs_abstract_conditioning_and_starts_as_the_plain_predictor():
    with pytest.raises(ValueError, match="needs abstract conditioning"):
        build_stdit(STDiTConfig(**{**STDIT_PRESETS["smoke"].__dict__, "subgoal_shift": True}), C, causal=False)
    torch.manual_seed(0)
    plain = randomized(build_stdit("smoke", C, causal=False, abstract_channels=3))
    torch.manual_seed(0)
    shifted = build_stdit(stdit_config("smoke", subgoal_shift=True), C, causal=False, abstract_channels=3)
    shifted.load_state_dict({**plain.state_dict(), **{k: v for k, v in shifted.state_dict().items()
                                                      if k.startswith("subgoal_shift.")}})
    x, tau = latents(2, 6, 1), torch.rand(2, 6)
    with torch.no_grad():
        out = plain(x, tau, **detail_inputs(2, 6, 2))
        torch.testing.assert_close(shifted(x, tau, **detail_inputs(2, 6, 2)), out)
        shifted.subgoal_shift.embed.weight.normal_()
        assert not torch.allclose(shifted(x, tau, **detail_inputs(2, 6, 2))[:, 3:], out[:, 3:])


def test_abstract_conditioning_resizes_grids_and_checks_slots():
    torch.manual_seed(0)
    model = randomized(build_stdit("smoke", C, causal=False, abstract_channels=3)).eval()
    x, tau = latents(2, 4, 1), torch.rand(2, 4)
    with torch.no_grad():
        out = model(x, tau, **detail_inputs(2, 4, 2, grid=(2, 3)))
    assert out.shape == x.shape and torch.isfinite(out).all()
    bad = detail_inputs(2, 4, 2)
    bad["cond_mask"][0, 0] = True
    with pytest.raises(ValueError, match="same number of conditioned slots"):
        model(x, tau, **bad)
    with pytest.raises(ValueError, match="needs cond_frames"):
        model(x, tau)


@pytest.mark.parametrize("preset", ["smoke", "default"])
def test_preset_shapes_and_probe_features(preset):
    torch.manual_seed(0)
    abstract = build_stdit(preset, 16, causal=True, steering=True)
    detail = build_stdit(preset, 16, causal=False, abstract_channels=16)
    d, depth = STDIT_PRESETS[preset].hidden_size, STDIT_PRESETS[preset].depth
    with torch.no_grad():
        x = latents(1, 6, 1, 16, 9, 16)
        assert abstract(x, torch.rand(1, 6), frame_rate=2.0, steering=torch.randn(1, 5, 2)).shape == x.shape
        x = latents(1, 10, 2, 16, 9, 16)
        cond = detail_inputs(1, 10, 3, 16, (9, 16))
        assert detail(x, torch.rand(1, 10), frame_rate=10.0, **cond).shape == x.shape
        features = detail(x, torch.rand(1, 10), **cond, features_from_block=min(4, depth))
        assert features.shape == (1, 10, d, 9, 16)
        # The linear-probe protocol: the image alone as the target frame, no context.
        single = abstract(x[:, :1], torch.zeros(1, 1), features_from_block=1)
        assert single.shape == (1, 1, d, 9, 16)
    with pytest.raises(ValueError, match="features_from_block"):
        abstract(x[:, :1], torch.zeros(1, 1), features_from_block=depth + 1)


def test_patches_and_probe_features_keep_the_grid_layout():
    x = latents(2, 3, 1, 4, 6, 8)
    tokens = patchify(x, 2)
    assert tokens.shape == (2, 3, 12, 16) and torch.equal(unpatchify(tokens, 2, 4, 6, 8), x)
    assert torch.equal(tokens[0, 0, 1, :4], x[0, 0, :, 0, 2])  # token 1 = patch row 0, column 1
    torch.manual_seed(0)
    model = randomized(build_stdit(stdit_config("smoke", patch_size=2), 4, causal=True)).eval()
    seen = []
    model.final_layer.register_forward_hook(lambda module, args, out: seen.append(args[0]))
    tau = torch.rand(2, 3)
    with torch.no_grad():
        model(x, tau)
        features = model(x, tau, features_from_block=1)
    assert features.shape == (2, 3, 64, 3, 4)
    torch.testing.assert_close(features[:, :, :, 1, 2], seen[0][:, :, 1 * 4 + 2])


def test_paper_preset_parameter_counts():
    with torch.device("meta"):
        abstract = n_params(build_stdit("paper", 16, causal=True))
        detail = n_params(build_stdit("paper", 16, causal=False, abstract_channels=16))
    assert abs(abstract / 512e6 - 1) < 0.05
    assert abs(detail / 555e6 - 1) < 0.05
    assert abs((detail - abstract) / 43e6 - 1) < 0.1  # the paper's extra conditioning parameters


def test_preset_overrides_are_checked():
    cfg = stdit_config("smoke", depth=3, mlp_ratio=2)
    assert (cfg.depth, cfg.mlp_ratio, cfg.hidden_size) == (3, 2.0, STDIT_PRESETS["smoke"].hidden_size)
    assert isinstance(cfg.mlp_ratio, float) and STDIT_PRESETS["smoke"].depth == 2  # a copy; presets stay
    with pytest.raises(ValueError, match=r"ST-DiT: unknown key 'hiden_size' \(known: abstract_positions, "):
        stdit_config("smoke", hiden_size=3)
    with pytest.raises(ValueError, match=r"ST-DiT: depth must be int, got 2.5 \(float\)"):
        stdit_config("smoke", depth=2.5)
    with pytest.raises(ValueError, match="ST-DiT: hidden_size must be int, got True"):
        STDIT_PRESETS["smoke"].with_overrides(hidden_size=True)
    with pytest.raises(ValueError, match="ST-DiT: hidden_size = 66 is not divisible by num_heads = 4"):
        stdit_config("smoke", hidden_size=66, num_heads=4)
    with pytest.raises(ValueError, match="ST-DiT: depth = 0 must be positive"):
        STDiTConfig(hidden_size=64, depth=0, num_heads=2, cond_dim=32)
    with pytest.raises(ValueError, match="ST-DiT: unknown preset 'huge'"):
        build_stdit("huge", 16, causal=True)


def test_predictor_file_build_dicts_rebuild_the_sized_network(tmp_path):
    """A file's ``build`` holds the preset, its overrides and the wiring; loading rebuilds the same network."""
    build = {"preset": "smoke", "latent_channels": 4, "causal": False, "abstract_channels": 4, "steering": False,
             "hidden_size": 32, "cond_dim": 16}
    model = build_stdit_from(build)
    assert (model.hidden_size, len(model.blocks)) == (32, 2)
    save_predictor(tmp_path / "p.pt", model, build, {})
    loaded = load_predictor(tmp_path / "p.pt")
    assert loaded.build == build and loaded.model.state_dict().keys() == model.state_dict().keys()


def test_smoke_model_overfits_a_fixed_batch_with_teacher_forcing():
    torch.manual_seed(0)
    model = build_stdit("smoke", C, causal=True)
    frames = latents(4, 4, 1)
    context, target = frames[:, :3], frames[:, 3:]

    def evaluate() -> float:
        with torch.no_grad():
            g = torch.Generator().manual_seed(123)
            return sum(teacher_forcing_loss(model, context, target, g)[0].item() for _ in range(8)) / 8

    initial = evaluate()
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(7)
    for _ in range(250):
        optimizer.zero_grad()
        loss, _ = teacher_forcing_loss(model, context, target, g)
        loss.backward()
        optimizer.step()
    final = evaluate()
    assert math.isfinite(final) and final < 0.3 * initial, (initial, final)


def test_authors_options_are_checked():
    """The settings of the authors' released networks (orbis2.models.official) refuse values they do not know."""
    with pytest.raises(ValueError, match="ST-DiT: qk_norm = 'group' must be one of layer, rms"):
        stdit_config("smoke", qk_norm="group")
    with pytest.raises(ValueError, match=r"ST-DiT: rate_range = \(15.0, 2.0\) must be \(low, high\)"):
        stdit_config("smoke", rate_range=(15, 2))


def test_additive_causal_mask_leaks_the_future_and_the_hard_one_does_not():
    """The authors' "causal" float mask adds +1 to the allowed scores: later frames still reach earlier ones."""
    torch.manual_seed(0)
    hard = randomized(build_stdit("smoke", C, causal=True)).eval()
    leaky = build_stdit(stdit_config("smoke", causal_mask="additive"), C, causal=True).eval()
    leaky.load_state_dict(hard.state_dict())
    x, tau = latents(1, 4, 2), torch.rand(1, 4)
    changed = x.clone()
    changed[:, -1] += 1.0
    with torch.no_grad():
        assert torch.equal(hard(x, tau)[:, :3], hard(changed, tau)[:, :3])
        assert (leaky(x, tau)[:, :3] - leaky(changed, tau)[:, :3]).abs().max() > 1e-4
    assert not leaky.uses_kv_cache(True) and hard.uses_kv_cache(True)


def test_a_saved_predictor_names_its_whole_size_and_an_older_file_stops_with_a_line(tmp_path, monkeypatch):
    """A file records every size setting (full_build), so it loads as what was trained even when a preset or a
    default changes later; a file that recorded only its overrides, from before the LayerNorm q/k norms became
    the default, stops with one line naming it."""
    build = {**full_build(STDIT_PRESETS, "smoke", {"qk_norm": "rms"}), "latent_channels": 4, "causal": True}
    assert build["qk_norm"] == "rms" and build["rate_encoding"] == "interleaved" and build["depth"] == 2
    model = build_stdit_from(build)
    save_predictor(tmp_path / "new.pt", model, build, {})
    monkeypatch.setitem(STDIT_PRESETS, "smoke", stdit_config("smoke", depth=3, rate_encoding="geometric"))
    loaded = load_predictor(tmp_path / "new.pt").model
    assert len(loaded.blocks) == 2 and loaded.rate_encoding == "interleaved"
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), model.state_dict().values()))
    save_predictor(tmp_path / "old.pt", model, {"preset": "smoke", "latent_channels": 4, "causal": True}, {})
    with pytest.raises(OrbisError, match=r"old\.pt: its weights do not fit the predictor its build describes "
                                         r"\(.*q_norm.bias.*\).*run its training stage again"):
        load_predictor(tmp_path / "old.pt")
