"""Known answers for the conditioning diagnostics: a model that ignores its input shows no material gap,
one that uses it does; the one-step mean of an exact velocity field is the conditional mean; the
ego-motion probe recovers a linear signal; energy shares of constructed latents; the latent steering
response is about 1 for latents that move like real ones and about 0 for latents that ignore steering."""

import importlib.util

import numpy as np
import pytest
import torch

from orbis2.errors import OrbisError
from orbis2.eval.metrics.ego_motion import (
    ego_motion_pairs,
    ego_motion_probe,
    probe_features,
    ridge_fit,
    ridge_path,
    ridge_predict,
    select_penalty,
    weighted_r2,
)
from orbis2.eval.protocols.conditioning import (
    effect_rows,
    energy_shares,
    evaluate_predictor,
    flow_loss,
    latent_statistics,
    latent_steering_response,
    latent_templates,
    one_step_mean,
    predictor_rows,
    probe_readout,
    sideways_shift,
    swapped,
    val_window_pairs,
    variant_errors,
)
from orbis2.eval.records import BaselineRow, ConditioningRecord, VariantRow, from_json
from orbis2.latents import open_cache
from orbis2.models.deviations import translate_columns
from orbis2.models.files import load_predictor
from orbis2.registry import registry
from orbis2.stage import PREDICTOR_FILE

from conftest import ROOT

CLIPS, PER_CLIP, N_CONTEXT, N_TARGET, SHAPE = 8, 4, 2, 3, (2, 3, 4)


def oracle(predict):
    """A velocity field that is exact for targets equal to ``predict(context, **cond)``: v = (x - m) / tau."""

    def model_fn(x, tau, **cond):
        m = predict(x[:, :N_CONTEXT], **cond)[:, None].expand(-1, x.shape[1], *SHAPE)
        t = tau.clamp(min=1e-3).reshape(*tau.shape, 1, 1, 1)
        return (x - m) / t

    return model_fn


def uses_subgoal(context, subgoal, **_):
    return subgoal


def ignores_subgoal(context, subgoal, **_):
    return context[:, -1]


@pytest.fixture
def windows():
    gen = torch.Generator().manual_seed(0)
    labels = np.repeat([f"clip{c}" for c in range(CLIPS)], PER_CLIP)
    subgoal = torch.randn(CLIPS, *SHAPE, generator=gen).repeat_interleave(PER_CLIP, 0)
    context = torch.randn(len(labels), N_CONTEXT, *SHAPE, generator=gen)
    target = subgoal[:, None] + 0.05 * torch.randn(len(labels), N_TARGET, *SHAPE, generator=gen)
    eps = torch.randn(3, len(labels), N_TARGET, *SHAPE, generator=gen)
    tau = torch.rand(3, len(labels), generator=gen)
    return labels, subgoal, context, target, eps, tau


def test_one_step_mean_of_an_exact_field_is_the_conditional_mean(windows):
    labels, subgoal, context, target, eps, tau = windows
    model = oracle(uses_subgoal)
    mean = one_step_mean(model, context, eps[0], subgoal=subgoal)
    assert torch.allclose(mean, subgoal[:, None].expand_as(mean), atol=1e-5)
    exact = subgoal[:, None].expand_as(target)
    assert flow_loss(model, context, exact, eps[0], tau[0], subgoal=subgoal).abs().max() < 1e-8


def run_variants(model, windows):
    labels, subgoal, context, target, eps, tau = windows
    variants = {"true": {"subgoal": subgoal}, "subgoal_other_clip": {"subgoal": swapped(subgoal, labels, 3)}}
    errors, _ = variant_errors(model, context, target, variants, eps, tau)
    return {(r["metric"], r["variant"]): r for r in effect_rows("m", errors, "true", labels, 0.03, 300, 0)}


def test_a_model_that_uses_its_subgoal_shows_a_material_gap(windows):
    rows = run_variants(oracle(uses_subgoal), windows)
    for metric in ("loss", "one_step_mse"):
        row = rows[metric, "subgoal_other_clip"]
        assert row["verdict"] == "used" and row["low"] > 1.0


def test_a_model_that_ignores_its_subgoal_shows_no_material_gap(windows):
    rows = run_variants(oracle(ignores_subgoal), windows)
    for metric in ("loss", "one_step_mse"):
        row = rows[metric, "subgoal_other_clip"]
        assert row["verdict"] == "not shown" and abs(row["effect"]) < 1e-6


def test_swapped_values_come_from_other_clips(windows):
    labels, subgoal = windows[0], windows[1]
    other = swapped(subgoal, labels, 1)
    clip_of = {tuple(s.flatten().tolist()): c for s, c in zip(subgoal, labels)}
    assert all(clip_of[tuple(o.flatten().tolist())] != c for o, c in zip(other, labels))


def test_ego_motion_probe_recovers_a_linear_signal_and_not_a_shuffled_one():
    rng = np.random.default_rng(0)
    weights = rng.normal(size=(12, 2))

    def make(n):
        x = rng.normal(size=(n, 12))
        return x, x @ weights + 0.05 * rng.normal(size=(n, 2))

    train, val = make(400), make(160)
    result, model = ego_motion_probe(train, val, np.repeat(np.arange(16), 10), penalty=1.0, reps=100, seed=0)
    for name in ("speed", "yaw_rate"):
        assert result[name]["r2"] > 0.95 and result[name]["low"] > 0.9
        assert result[name]["shuffled_r2"] < 0.2
    # The probe and its shuffled control share one SVD of the train features: the same bits as two fits.
    control = ridge_fit(train[0], train[1][np.random.default_rng(0).permutation(400)], 1.0)
    assert all(np.array_equal(a, b) for a, b in zip(model, ridge_fit(*train, 1.0)))
    shuffled = ridge_predict(control, val[0])
    assert [result[name]["shuffled_r2"] for name in ("speed", "yaw_rate")] == [
        weighted_r2(val[1][:, k], shuffled[:, k], np.ones(160)) for k in range(2)]


def test_ego_motion_pairs_pair_latents_a_step_apart_with_the_mean_motion_between():
    lat = np.arange(6, dtype=np.float64).reshape(6, 1, 1, 1) * np.ones((6, 1, 2, 4))
    odo = np.stack([np.arange(6.0), -np.arange(6.0)], axis=1)
    odo[5] = np.nan  # a missing row after the last pair's interval: still usable
    x, y, clips = ego_motion_pairs([lat], [odo], ["a"], step=2, stride=1, strips=2)
    assert x.shape == (4, 4) and list(clips) == ["a"] * 4
    assert x[1].tolist() == [1.0, 1.0, 3.0, 3.0]
    assert y[1].tolist() == [1.5, -1.5]
    assert probe_features(np.arange(8.0).reshape(1, 1, 1, 8), 4).tolist() == [[0.5, 2.5, 4.5, 6.5]]
    assert probe_features(np.arange(8.0).reshape(1, 2, 1, 4), 0).tolist() == [list(range(8))]


def test_energy_shares_of_constructed_latents():
    template = np.zeros((1, 2, 2))
    # Each clip is a constant offset from the template: all variation is between clips, none frame to frame.
    clips = [np.full((5, 1, 2, 2), v) for v in (1.0, -1.0, 2.0)]
    shares = energy_shares(clips, template, step=2)
    assert shares["varying_share"] == pytest.approx(1.0)
    assert shares["within_clip_share"] == pytest.approx(0.0)
    assert shares["repeat_last_mse"] == pytest.approx(0.0)
    shares = energy_shares([np.full((5, 1, 2, 2), 1.0)], np.full((1, 2, 2), 0.5), step=1)
    assert shares["varying_share"] == pytest.approx(0.25)
    with pytest.raises(ValueError):
        energy_shares([np.zeros((3, 1, 2, 2))], template, step=1)


MODES = {"original": [1.0, 1.0], "speed_x0.5": [0.5, 1.0], "speed_x1.5": [1.5, 1.0],
         "yaw_rate_x0.5": [1.0, 0.5], "yaw_rate_x1.5": [1.0, 1.5]}


def steering_windows(follows: bool, clips: int = 16, per_clip: int = 8):
    """Readouts of a probe with gain 0.6 on speed and 0.5 on yaw rate (plus noise): from real next latents, and
    from a model's latents under each mode that move like real ones (``follows``) or not at all."""
    rng = np.random.default_rng(1)
    n = clips * per_clip
    commanded = np.stack([rng.uniform(2, 12, n), rng.choice([-1, 1], n) * rng.uniform(0.1, 0.8, n)], axis=1)
    commanded[::7, 1] = 0.0  # straight windows: left out of the yaw response
    commanded[3] = np.nan  # unknown steering: left out
    gain = np.array([0.6, 0.5, 3.0])  # speed and yaw rate (probe), sideways columns per rad/s

    def read(motion):
        return gain * motion[:, [0, 1, 1]] + 0.02 * rng.normal(size=(n, 3))

    readouts = {"commanded": commanded, "real": read(commanded)}
    for mode, factors in MODES.items():
        readouts[mode] = read(commanded * np.array(factors) if follows else commanded)
    return readouts, np.repeat([f"clip{c}" for c in range(clips)], per_clip)


@pytest.mark.parametrize("follows", [True, False])
def test_latent_steering_response_is_one_for_real_like_latents_and_zero_for_ignored_steering(follows):
    readouts, clips = steering_windows(follows)
    result = latent_steering_response(readouts, MODES, clips, reps=200, seed=0, material=0.25)
    assert result["gain"]["speed"] == pytest.approx(0.6, abs=0.02)
    assert result["gain"]["yaw_rate"] == pytest.approx(0.5, abs=0.05)
    assert result["gain"]["sideways_shift"] == pytest.approx(3.0, abs=0.2)
    yaw = result["responses"]["yaw_rate"]
    assert yaw["windows"] == sum(1 for v in readouts["commanded"][:, 1] if np.isfinite(v) and abs(v) > 0.05)
    for name in ("speed", "yaw_rate", "sideways_shift"):
        response = result["responses"][name]
        assert response["low"] <= response["relative"] <= response["high"]
        if follows:
            assert response["relative"] == pytest.approx(1.0, abs=0.1) and response["verdict"] == "used"
        else:
            assert abs(response["relative"]) < 0.1 and response["verdict"] == "not shown"
    # The drive's own turn direction counts positive: a real drive reads as a positive yaw rate.
    assert result["modes"]["real"]["yaw_rate"] > 0 and result["modes"]["commanded"]["yaw_rate"] > 0
    for response in result["responses"].values():  # each half step on the real-difference scale
        assert response["ordered"] is follows
        for step in response["steps"].values():
            assert step["relative"] == pytest.approx(1.0 if follows else 0.0, abs=0.15)


def test_a_response_that_saturates_at_the_original_is_not_ordered():
    """x0.5 < original = x1.5: the whole response is half the real one, its upper step is nothing."""
    readouts, clips = steering_windows(True)
    readouts["yaw_rate_x1.5"] = readouts["original"]
    yaw = latent_steering_response(readouts, MODES, clips, reps=200, seed=0, material=0.25)["responses"]["yaw_rate"]
    assert yaw["relative"] == pytest.approx(0.5, abs=0.1) and yaw["verdict"] == "used" and not yaw["ordered"]
    assert yaw["steps"]["yaw_rate_x1.5 - original"]["verdict"] == "not shown"
    assert yaw["steps"]["original - yaw_rate_x0.5"]["relative"] == pytest.approx(1.0, abs=0.15)


def test_latent_steering_response_without_turning_windows_is_none():
    readouts, clips = steering_windows(True)
    readouts = {k: v.copy() for k, v in readouts.items()}
    readouts["commanded"][:, 1] = 0.0
    result = latent_steering_response(readouts, MODES, clips, reps=50, seed=0, material=0.25)
    assert result["responses"]["yaw_rate"] is None and result["responses"]["sideways_shift"] is None
    assert result["responses"]["speed"] is not None
    readouts["commanded"][:4, 1] = 0.5  # turning windows of one clip only: no interval over clips
    result = latent_steering_response(readouts, MODES, clips, reps=50, seed=0, material=0.25)
    assert result["responses"]["sideways_shift"] is None and result["responses"]["speed"] is not None


def test_the_probe_penalty_is_chosen_on_held_out_train_clips():
    """400 pairs, 300 features, one carrying the signal: no penalty overfits, a huge one predicts the mean."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(400, 300))
    y = np.stack([x[:, 0], -x[:, 0]], axis=1) + 0.3 * rng.normal(size=(400, 2))
    clips = np.repeat(np.arange(40), 10)
    penalties, scores = select_penalty(x, y, clips, [1e-3, 10.0, 300.0, 1e7], folds=4, seed=0)
    assert penalties == [10.0, 10.0] and [list(s) for s in scores] == [[1e-3, 10.0, 300.0, 1e7]] * 2
    for target in scores:
        assert target[10.0] > 0.6  # the signal explains ~90% of each target's variance
        assert target[1e-3] < 0 and abs(target[1e7]) < 0.05 and target[300.0] < target[10.0]
    with pytest.raises(ValueError, match="needs >= 4 train clips"):
        select_penalty(x, y, np.repeat(np.arange(3), 134)[:400], [1.0], folds=4, seed=0)


@pytest.mark.parametrize("pairs, features", [(60, 200), (200, 60)])  # fewer pairs than features, and more
def test_the_ridge_path_solves_the_normal_equations(pairs, features):
    """The SVD path gives the weights of (z^T z + p I) w = z^T (y - mean y), z the standardised features."""
    rng = np.random.default_rng(5)
    x, y = rng.normal(2.0, 3.0, size=(pairs, features)), rng.normal(size=(pairs, 2))
    z = (x - x.mean(axis=0)) / (x.std(axis=0) + 1e-8)
    for penalty, (mean, scale, weights, bias) in zip((0.1, 10.0, 1e4), ridge_path(x, y, (0.1, 10.0, 1e4))):
        np.testing.assert_allclose(mean, x.mean(axis=0))
        np.testing.assert_allclose(scale, x.std(axis=0) + 1e-8)
        expected = np.linalg.solve(z.T @ z + penalty * np.eye(features), z.T @ (y - y.mean(axis=0)))
        np.testing.assert_allclose(weights, expected, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(bias, y.mean(axis=0))
    with pytest.raises(ValueError, match="must be > 0"):
        ridge_path(x, y, [0.0])


def test_each_probe_target_gets_its_own_penalty():
    """A target carried by one feature wants a weak penalty; one spread thinly over all 300 (each weight tiny,
    the sum large) wants a strong one: a shared penalty would serve one of them badly."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(400, 300))
    sparse = 3.0 * x[:, 0] + 0.3 * rng.normal(size=400)
    spread = x.mean(axis=1) * 17.0 + 1.0 * rng.normal(size=400)
    y = np.stack([sparse, spread], axis=1)
    clips = np.repeat(np.arange(40), 10)
    penalties, scores = select_penalty(x, y, clips, [1.0, 30.0, 1000.0, 30000.0], folds=4, seed=0)
    assert penalties[0] < penalties[1]
    model = ridge_fit(x, y, penalties)
    for j, penalty in enumerate(penalties):  # each column is the single-penalty fit of its own target
        np.testing.assert_allclose(model[2][:, j], ridge_fit(x, y, penalty)[2][:, j])


def test_sideways_shift_reads_a_known_translation():
    rng = torch.Generator().manual_seed(0)
    before = torch.sin(torch.linspace(0, 6, 16) + torch.randn(3, 4, 5, 1, generator=rng))  # varies across columns
    moved = torch.tensor([2.0, -1.25, 0.0])
    after = translate_columns(before, moved)
    np.testing.assert_allclose(sideways_shift(before, after), moved.numpy())


@pytest.mark.parametrize("shape", [(3, 4, 5, 16), (98, 8, 16, 28), (2, 1, 1, 7)])
def test_translation_grid_is_affine_grids_bit_for_bit(shape):
    """translate_columns builds its grid by broadcasting: the same samples as through ``F.affine_grid``."""
    rng = torch.Generator().manual_seed(1)
    x, columns = torch.randn(shape, generator=rng), 4 * torch.randn(shape[0], generator=rng)
    theta = torch.zeros(shape[0], 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0
    theta[:, 0, 2] = -2.0 * columns / max(shape[-1] - 1, 1)
    grid = torch.nn.functional.affine_grid(theta, [shape[0], 1, *shape[2:]], align_corners=True)
    expected = torch.nn.functional.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    torch.testing.assert_close(translate_columns(x, columns), expected, rtol=0, atol=0)


def test_probe_readout_applies_the_probe_to_a_latent_pair():
    rng = np.random.default_rng(2)
    before, after = rng.normal(size=(64, 2, 3, 4)), rng.normal(size=(64, 2, 3, 4))
    features = np.concatenate([before.reshape(64, -1), after.reshape(64, -1)], axis=1)
    targets = features @ rng.normal(size=(48, 2))
    probe = ridge_fit(features, targets, 1e-6)
    read = probe_readout(probe, torch.from_numpy(before), torch.from_numpy(after), strips=0)
    np.testing.assert_allclose(read, targets, atol=1e-3)


@pytest.mark.slow
def test_the_all_scope_takes_the_main_rows_a_fresh_evaluation_gives(smoke_main, smoke_cfg):
    """eval_conditioning_all takes the main predictors' rows and the latent statistics from the main scope's
    record (--main-record, as the DAG passes it) instead of evaluating them again. That is exact because a
    predictor's rows depend on it alone (its own noise draws and bootstrap): the hierarchy's bottom predictor
    evaluated here alone, and the latent statistics made again, equal the main job's record bit for bit."""
    record = from_json(ConditioningRecord, smoke_main / "reports/eval/conditioning.json")
    ev, data, settings = smoke_cfg.evaluation, smoke_cfg.data, smoke_cfg.evaluation.conditioning
    cache = open_cache(smoke_main / "data/latents")
    first, second, keys = val_window_pairs(cache, data, settings)
    templates = latent_templates(cache)
    latents, _ = latent_statistics(cache, data, settings, ev.seed, templates)
    assert ConditioningRecord.model_validate({**record.model_dump(), "latents": latents}) == record
    predictor = load_predictor(smoke_main / "data/predictors/detail" / PREDICTOR_FILE, torch.device("cpu"))
    per_seed = [evaluate_predictor("detail", predictor, first, second, keys, templates, data, settings, seed,
                                   torch.device("cpu")) for seed in ev.seeds]
    variants, baselines = predictor_rows("detail", per_seed, keys, settings.threshold, settings.bootstrap_reps,
                                         ev.seed)
    assert variants and baselines
    assert [VariantRow.model_validate(row) for row in variants] == [r for r in record.variants if r.model == "detail"]
    assert [BaselineRow.model_validate(row) for row in baselines] == [r for r in record.baselines
                                                                       if r.model == "detail"]
    # A record of other settings or other predictors is refused, naming the file.
    spec = importlib.util.spec_from_file_location("stage_eval_conditioning", ROOT / "stages/eval_conditioning.py")
    stage = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(stage)
    path = smoke_main / "reports/eval/conditioning.json"
    main = registry().conditioning_predictors("main")
    assert stage.main_rows(path, main, keys, settings, ev.seeds) == record
    for names, seeds in ((main[:-1], ev.seeds), (main, [*ev.seeds, 7])):
        with pytest.raises(OrbisError, match=r"conditioning\.json was made with other settings or predictors"):
            stage.main_rows(path, names, keys, settings, seeds)
