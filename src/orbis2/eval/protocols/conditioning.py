"""Does each predictor use its inputs, and does it beat trivial predictions? (the ``eval_conditioning`` stage)

Generated-video metrics cannot separate "the model ignores its conditioning" from
"the conditioning carries little"; this stage measures it directly on real val
windows, as the predictors see them (scaled cached latents):

- **Variants.** The same windows and the same noise draws (``draws`` per window)
  under the true conditioning and under altered ones: for the detail predictor a
  subgoal taken from ANOTHER clip, or none; for the steered abstract predictor
  null steering, another clip's steering, yaw rate negated, speed halved. Two
  errors per window: the flow-matching loss (eq. 1 with the window's tau) and
  the error of the one-step conditional mean. Swaps always come from another
  clip (:func:`orbis2.eval.metrics.stats.other_clip_donors`): windows of the same clip a
  fraction of a second apart carry nearly the same subgoal.
- **One-step conditional mean.** At tau = 1 the input is pure noise, so a
  perfect velocity field gives ``eps - v(eps, 1) = E[x | context, conditioning]``;
  its MSE to the target is the conditional variance, the lowest any predictor
  can reach. A *sample*'s MSE is twice that, which is why comparing a sample
  with "repeat the last frame" is biased against the model. Every main predictor
  is compared at 0.5 s and 1 s ahead (the 1-s figure feeds the first step's
  conditional mean back as context, with the true conditioning of the next
  window) with repeating the last context frame and with the dataset mean.
- **Latents.** How much of each latent set's energy varies frame to frame around
  a fixed per-position template (the train mean per position and channel), how
  much of that variation is within a clip, the repeat-last MSE at 0.5 s, and a
  ridge probe of ego-motion (speed, yaw rate over 0.5 s) from two abstract latents
  0.5 s apart, on the whole latent grid (or pooled to vertical strips x channels with
  ``strips`` > 0; trained on train with the penalty that predicts held-out train
  clips best, R^2 on val).
- **Steering inside the model.** The steered predictor's one-step mean under each
  of ``evaluation.steering_modes`` (speed or yaw rate scaled), read by that
  ego-motion probe: which motion do its predicted abstract latents show, against
  what the probe reads from the real next latents of the same drives? The probe is
  linear, so its reading of the conditional mean is the mean reading over the
  model's predictions. Paired per window: the yaw rate read under yaw x1.5 minus
  x0.5 (turning windows, the drive's turn direction positive) and the speed read
  under speed x1.5 minus x0.5, each relative to the difference the probe reads
  from real drives with that motion (its gain on real pairs times the commanded
  difference): 1 means the predicted latents move like real ones. A second reading
  of the turn needs no probe: the sideways shift (in grid columns) that best maps
  the last context latent onto the predicted one, against the shift of the real
  next latent. The probe, fitted on real pairs, can misread blurred conditional
  means; the shift reads the translation a turn causes directly.

Effects are relative to the true-conditioning error, with clip-bootstrap
intervals; an input is "used" when the lower bound exceeds ``threshold``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from orbis2.config.sections import DataConfig
from orbis2.data.motion import TURN_THRESHOLD
from orbis2.errors import OrbisError
from orbis2.eval.metrics.ego_motion import (
    EGO_MOTION_TARGETS,
    ego_motion_pairs,
    ego_motion_probe,
    probe_features,
    ridge_predict,
    select_penalty,
)
from orbis2.eval.metrics.stats import (
    bootstrap_statistic,
    decide,
    other_clip_donors,
    relative_difference,
)
from orbis2.eval.records import ConditioningRecord
from orbis2.flow import interpolate
from orbis2.hierarchy import (
    detail_condition,
    rate_geometry,
    raw_steering,
    scale_steering,
    steering_interval,
    window_key,
)
from orbis2.latents import KINDS, LatentCache, LatentWindowDataset, collate
from orbis2.models.deviations import best_sideways_shift
from orbis2.registry import registry

ModelFn = Callable[..., torch.Tensor]
METRICS = ("loss", "one_step_mse")


MOVING_SPEED = 0.5  # m/s: a window "moves" above this mean speed


# --------------------------------------------------------------------------- per-window errors


def one_step_mean(model_fn: ModelFn, context: torch.Tensor, eps: torch.Tensor, **cond) -> torch.Tensor:
    """One Euler step from pure noise: x_hat = eps - v(eps, tau = 1), the conditional mean of the targets."""
    b, n_context = context.shape[:2]
    tau = torch.cat([torch.zeros(b, n_context), torch.ones(b, eps.shape[1])], dim=1).to(context)
    velocity = model_fn(torch.cat([context, eps], dim=1), tau, **cond)[:, n_context:]
    return eps - velocity.to(eps.dtype)


def flow_loss(model_fn: ModelFn, context: torch.Tensor, target: torch.Tensor, eps: torch.Tensor,
              tau: torch.Tensor, **cond) -> torch.Tensor:
    """Per-window eq. 1 loss [B] at target noise level ``tau`` [B], clean context."""
    b, n_context = context.shape[:2]
    tau_target = tau[:, None].expand(b, target.shape[1])
    x = torch.cat([context, interpolate(target, eps, tau_target)], dim=1)
    tau_all = torch.cat([torch.zeros(b, n_context).to(tau), tau_target], dim=1)
    velocity = model_fn(x, tau_all, **cond)[:, n_context:]
    return per_window_mse(velocity, eps - target)


def per_window_mse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ((a.float() - b.float()) ** 2).flatten(1).mean(dim=1)


@torch.no_grad()
def variant_errors(model_fn: ModelFn, context: torch.Tensor, target: torch.Tensor,
                   variants: dict[str, dict[str, Any]], eps: torch.Tensor, tau: torch.Tensor
                   ) -> tuple[dict[str, dict], dict[str, torch.Tensor]]:
    """Per variant, per-window loss and one-step-mean MSE [B] averaged over the draws eps [K, B, ...], tau [K, B],
    and per variant the one-step mean averaged over the draws (the horizons reuse the true one's).

    Every variant sees exactly the same draws, so their differences are paired.
    """
    errors, means = {}, {}
    for name, cond in variants.items():
        loss = torch.stack([flow_loss(model_fn, context, target, e, t, **cond) for e, t in zip(eps, tau)]).mean(0)
        draws = torch.stack([one_step_mean(model_fn, context, e, **cond) for e in eps])
        mse = torch.stack([per_window_mse(d, target) for d in draws]).mean(0)
        errors[name] = {"loss": loss.cpu().numpy(), "one_step_mse": mse.cpu().numpy()}
        means[name] = draws.mean(0)
    return errors, means


def concat_errors(parts: list[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Join per-batch ``variant_errors`` results along the window axis."""
    return {v: {m: np.concatenate([p[v][m] for p in parts]) for m in parts[0][v]} for v in parts[0]}


def mean_over_seeds(per_seed: list[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Average each window's errors over seeds (more draws per window; the windows stay the units)."""
    return {v: {m: np.mean([s[v][m] for s in per_seed], axis=0) for m in per_seed[0][v]} for v in per_seed[0]}


def effect_rows(model: str, errors: dict[str, dict[str, np.ndarray]], reference: str, clusters, threshold: float,
                reps: int, seed: int, per_seed: list[dict[str, dict[str, np.ndarray]]] | None = None) -> list[dict]:
    """Rows (model, metric, variant, errors, relative effect vs ``reference`` with its interval, verdict).

    effect = (error without the true input - error with it) / error with it; "used"
    when the interval's lower bound clears ``threshold``. ``per_seed`` adds each
    seed's verdict (do the seeds agree?).
    """
    rows = []
    for metric in METRICS:
        ref = errors[reference][metric]
        rows.append({"model": model, "metric": metric, "variant": reference, "error": float(ref.mean()),
                     "effect": 0.0, "low": 0.0, "high": 0.0, "verdict": "reference", "windows": len(ref)})
        for variant in errors:
            if variant == reference:
                continue
            iv = relative_difference(errors[variant][metric], ref, clusters, reps, seed=seed)
            row = {"model": model, "metric": metric, "variant": variant, "error": float(errors[variant][metric].mean()),
                   "effect": iv.estimate, "low": iv.low, "high": iv.high, "verdict": decide(iv, threshold),
                   "windows": len(ref), "clips": iv.clusters}
            if per_seed is not None:
                row["seed_verdicts"] = [decide(relative_difference(s[variant][metric], s[reference][metric], clusters,
                                                                   reps, seed=seed), threshold) for s in per_seed]
            rows.append(row)
    return rows


def baseline_rows(model: str, horizon_s: float, model_err: np.ndarray, baselines: dict[str, np.ndarray], clusters,
                  threshold: float, reps: int, seed: int) -> list[dict]:
    """Does the one-step conditional mean beat each trivial prediction by a material margin?

    effect = (baseline error - model error) / model error; "holds" when its lower bound
    clears ``threshold``, "does not hold" when the whole interval is below it.
    """
    rows = []
    for name, err in baselines.items():
        iv = relative_difference(err, model_err, clusters, reps, seed=seed)
        rows.append({"model": model, "horizon_s": horizon_s, "baseline": name, "model_mse": float(model_err.mean()),
                     "baseline_mse": float(err.mean()), "effect": iv.estimate, "low": iv.low, "high": iv.high,
                     "verdict": decide(iv, threshold, "claim"), "windows": len(err), "clips": iv.clusters})
    return rows


# --------------------------------------------------------------------------- latent statistics


def energy_shares(clips: list[np.ndarray], template: np.ndarray, step: int) -> dict[str, float]:
    """How much of a latent set's energy moves, and how much of that moves within a clip.

    ``clips``: per clip, latents [T, ...] as the predictors see them; ``template``: the
    per-position, per-channel mean [...] (from train). ``varying_share`` = E|x - template|^2 /
    E|x|^2; ``within_clip_share`` = E|x - clip mean|^2 / E|x - template|^2;
    ``repeat_last_mse`` = E|x_t - x_{t - step}|^2 per element, also relative to the variation.
    """
    total = varying = within = repeat = 0.0
    elements = pairs = 0
    for x in clips:
        x = x.astype(np.float64)
        total += float((x ** 2).sum())
        varying += float(((x - template) ** 2).sum())
        within += float(((x - x.mean(axis=0)) ** 2).sum())
        elements += x.size
        if len(x) > step:
            repeat += float(((x[step:] - x[:-step]) ** 2).sum())
            pairs += x[step:].size
    if elements == 0 or varying == 0:
        raise ValueError("energy_shares needs at least one non-constant clip")
    variation = varying / elements
    repeat_mse = repeat / pairs if pairs else float("nan")
    return {"varying_share": varying / total, "within_clip_share": within / varying,
            "variation_mse": variation, "repeat_last_mse": repeat_mse,
            "repeat_last_relative": repeat_mse / variation, "frames": int(sum(len(x) for x in clips))}


# --------------------------------------------------------------------------- swaps


def swapped(values: torch.Tensor, clusters, seed: int) -> torch.Tensor:
    """Each window's ``values`` replaced by those of a window from another clip."""
    donors = torch.from_numpy(other_clip_donors(clusters, seed))
    return values[donors.to(values.device)]


# --------------------------------------------------------------------------- the stage


def val_window_pairs(cache: LatentCache, data: DataConfig, settings) -> tuple[dict, dict, np.ndarray]:
    """Val windows at anchors a (every ``anchor_stride``, at most ``max_windows``) and their successors a + 0.5 s.

    Returns both collated batches (all windows in memory) and each window's clip key.
    """
    dataset = LatentWindowDataset(cache, "val", data)
    advance = (data.detail_window - data.detail_context) * data.detail_stride
    position = {(int(c), int(a)): i for i, (c, a) in enumerate(dataset.items)}
    pairs = [(i, position[int(c), int(a) + advance]) for i, (c, a) in enumerate(dataset.items)
             if (int(c), int(a) + advance) in position and int(a) % settings.anchor_stride == 0]
    if len(pairs) > settings.max_windows:
        pairs = [pairs[int(k)] for k in np.linspace(0, len(pairs) - 1, settings.max_windows).round()]
    keys = np.array([dataset.keys[int(dataset.items[i][0])] for i, _ in pairs])
    if len(set(keys)) < 2:
        raise OrbisError(f"{cache.root}: the val split gives windows from {len(set(keys))} clip(s); the conditioning "
                         f"evaluation needs at least 2 clips (add val episodes or lower "
                         f"evaluation.conditioning.anchor_stride)")
    first = collate([dataset[i] for i, _ in pairs])
    second = collate([dataset[j] for _, j in pairs])
    return first, second, keys


def condition_variants(stage: str, meta: dict, window: dict, keys, data: DataConfig, seed: int,
                       frame_rate: float) -> dict[str, dict[str, Any]]:
    """Per variant the model's keyword inputs for ALL windows (sliced per batch later); "true" first."""
    base = {"frame_rate": frame_rate}
    spec = registry().predictors[stage]
    if spec.condition is not None:
        slow = window[window_key(spec.condition, "slow")]
        other = slow.clone()
        other[:, -1] = swapped(slow[:, -1], keys, seed)
        frames, mask = detail_condition(slow, data)
        other_frames, _ = detail_condition(other, data)
        return {"true": {**base, "cond_frames": frames, "cond_mask": mask},
                "subgoal_other_clip": {**base, "cond_frames": other_frames, "cond_mask": mask},
                "none": {**base, "cond_frames": torch.zeros_like(frames), "cond_mask": torch.zeros_like(mask)}}
    if spec.steering:
        raw, unknown = raw_steering(window["odometry"], window["has_odometry"], steering_interval(data))

        def steer(values: torch.Tensor, drop: torch.Tensor | None = None) -> dict[str, Any]:
            return steering_condition(meta, values, unknown if drop is None else drop, frame_rate)

        return {"true": steer(raw), "null": steer(torch.zeros_like(raw), torch.ones_like(unknown)),
                "steering_other_clip": steer(swapped(raw, keys, seed)),
                "yaw_rate_negated": steer(raw * raw.new_tensor([1.0, -1.0])),
                "speed_halved": steer(raw * raw.new_tensor([0.5, 1.0]))}
    return {"true": base}


def steering_condition(meta: dict, values: torch.Tensor, drop: torch.Tensor, frame_rate: float) -> dict[str, Any]:
    """A steered predictor's keyword inputs for raw steering ``values`` (scaled as its file records)."""
    scaled = torch.nan_to_num(scale_steering(values, meta["steering"]["scale"]))
    return {"frame_rate": frame_rate, "steering": scaled, "steering_drop": drop}


def _batch(cond: dict[str, Any], rows: slice, dev: torch.device) -> dict[str, Any]:
    return {k: v[rows].to(dev) if isinstance(v, torch.Tensor) else v for k, v in cond.items()}


@torch.no_grad()
def evaluate_predictor(stage: str, predictor, first: dict, second: dict, keys, templates: dict[str, torch.Tensor],
                       data: DataConfig, settings, seed: int, dev: torch.device) -> tuple[dict, dict]:
    """(variant errors per window, one-step-mean and baseline errors at 0.5 s and 1 s per window) for one seed."""
    spec = registry().predictors[stage]
    key, (rate, _, n_context) = window_key(spec.level, spec.rate), rate_geometry(data, spec.rate)
    model = predictor.model.eval()
    variants = condition_variants(stage, predictor.meta, first, keys, data, seed, float(rate))
    nexts = condition_variants(stage, predictor.meta, second, keys, data, seed, float(rate))["true"]
    generator = torch.Generator(dev).manual_seed(seed)
    template = templates[spec.level].to(dev)
    parts, ahead = [], {name: [] for name in ("model_0.5", "repeat_0.5", "mean_0.5", "model_1", "repeat_1", "mean_1")}
    k = settings.draws
    for start in range(0, len(keys), settings.batch_size):
        rows = slice(start, start + settings.batch_size)
        frames, frames2 = first[key][rows].to(dev), second[key][rows].to(dev)
        context, target = frames[:, :n_context], frames[:, n_context:]
        b = len(frames)
        eps = torch.randn((k, *target.shape), generator=generator, device=dev)
        tau = torch.rand((k, b), generator=generator, device=dev)
        cond = {name: _batch(v, rows, dev) for name, v in variants.items()}
        errors, means = variant_errors(model, context, target, cond, eps, tau)
        parts.append(errors)
        # Horizons: the frame 0.5 s after the last context frame, then 1 s (the first step's mean fed back).
        eps2 = torch.randn((k, *target.shape), generator=generator, device=dev)
        target2 = frames2[:, n_context:]
        mean1 = means["true"]
        context2 = torch.cat([context, mean1], dim=1)[:, -n_context:]
        mean2 = torch.stack([one_step_mean(model, context2, e, **_batch(nexts, rows, dev)) for e in eps2]).mean(0)
        last = context[:, -1]
        for horizon, pred, truth in (("0.5", mean1[:, -1], target[:, -1]), ("1", mean2[:, -1], target2[:, -1])):
            ahead[f"model_{horizon}"].append(per_window_mse(pred, truth).cpu().numpy())
            ahead[f"repeat_{horizon}"].append(per_window_mse(last, truth).cpu().numpy())
            ahead[f"mean_{horizon}"].append(per_window_mse(template.expand_as(truth), truth).cpu().numpy())
    return concat_errors(parts), {name: np.concatenate(v) for name, v in ahead.items()}


def probe_readout(probe: tuple[np.ndarray, ...], before: torch.Tensor, after: torch.Tensor, strips: int) -> np.ndarray:
    """The (speed, yaw rate) the ego-motion probe reads from latent pairs [B, C, h, w] -> [B, 2]."""
    features = [probe_features(t.float().cpu().numpy(), strips) for t in (before, after)]
    return ridge_predict(probe, np.concatenate(features, axis=1))


SHIFT_SEARCH = (4.0, 0.25)  # sideways shifts searched: up to 4 latent columns either way, in quarter columns


def sideways_shift(before: torch.Tensor, after: torch.Tensor,
                   search: tuple[float, float] = SHIFT_SEARCH) -> np.ndarray:
    """How far latents [B, C, h, w] moved sideways from ``before`` to ``after``, in grid columns [B].

    :func:`best_sideways_shift` over the ``search`` grid (reach, step); content moves right for positive
    values. A turn moves the whole abstract grid sideways (the default town: correlation 0.96 with
    the yaw rate), so this reads the turn directly, without a probe fitted on real latents.
    """
    return best_sideways_shift(before.float().cpu(), after.float().cpu(), *search).double().numpy()


def motion_readout(probe: tuple[np.ndarray, ...], before: torch.Tensor, after: torch.Tensor,
                   strips: int) -> np.ndarray:
    """Per latent pair [B, 3]: the probe's speed and yaw rate, and the sideways shift in columns."""
    return np.concatenate([probe_readout(probe, before, after, strips), sideways_shift(before, after)[:, None]], 1)


@torch.no_grad()
def steering_readouts(stage: str, predictor, window: dict, data: DataConfig, modes: dict[str, list[float]],
                      probe: tuple[np.ndarray, ...], settings, seed: int, dev: torch.device) -> dict[str, np.ndarray]:
    """The commanded motion per window [N, 2] (mean speed and yaw rate over the predicted interval; NaN if
    unknown), and per window [N, 3] the :func:`motion_readout` of the real next latent ("real") and of the
    steered predictor's one-step mean under each mode's scaled steering (the same noise draws for every mode)."""
    spec = registry().predictors[stage]
    key, (rate, _, n_context) = window_key(spec.level, spec.rate), rate_geometry(data, spec.rate)
    raw, unknown = raw_steering(window["odometry"], window["has_odometry"], steering_interval(data))
    model = predictor.model.eval()
    generator = torch.Generator(dev).manual_seed(seed)
    parts: dict[str, list[np.ndarray]] = {"real": [], **{mode: [] for mode in modes}}
    for start in range(0, len(raw), settings.batch_size):
        rows = slice(start, start + settings.batch_size)
        frames = window[key][rows].to(dev)
        context, target = frames[:, :n_context], frames[:, n_context:]
        eps = torch.randn((settings.draws, *target.shape), generator=generator, device=dev)
        parts["real"].append(motion_readout(probe, context[:, -1], target[:, -1], settings.strips))
        for mode, factors in modes.items():
            values = raw[rows].to(dev) * torch.tensor(factors, dtype=raw.dtype, device=dev)
            cond = steering_condition(predictor.meta, values, unknown[rows].to(dev), float(rate))
            mean = torch.stack([one_step_mean(model, context, e, **cond) for e in eps]).mean(0)
            parts[mode].append(motion_readout(probe, context[:, -1], mean[:, -1], settings.strips))
    return {"commanded": raw.double().mean(dim=1).numpy(), **{k: np.concatenate(v) for k, v in parts.items()}}


RESPONSES = {  # response name -> (column of the readout, column of the commanded motion)
    "speed": (0, 0),
    "yaw_rate": (1, 1),
    "sideways_shift": (2, 1),  # read directly from the latent grid, commanded by the yaw rate
}


def latent_steering_response(readouts: dict[str, np.ndarray], modes: dict[str, list[float]], clusters, reps: int,
                             seed: int, material: float) -> dict[str, Any]:
    """How the steered predictor's latents answer scaled steering, relative to how real latents move.

    For each of ``RESPONSES`` (speed on moving windows; yaw rate and sideways shift on
    turning windows, each drive's turn direction positive): the reading under x1.5 minus
    under x0.5, paired per window, over what real drives with that motion difference show
    (the least-squares gain from commanded motion to the reading of the real next latents,
    times the commanded difference). 1: the predicted latents move like real ones; 0:
    steering is ignored. "used" when the interval's lower bound clears ``material``. Each
    response also splits into its two steps, x1.5 minus the original and the original minus
    x0.5 (``steps``, on the same scale: each over the real difference for half the commanded
    motion); "ordered" when both steps' lower bounds clear ``material``. A response is None
    where the qualifying windows come from fewer than two clips (no interval over clips), the
    modes are missing, or the reading of real latents does not grow with the motion (gain <= 0).
    """
    commanded, real = readouts["commanded"], readouts["real"]
    clusters = np.asarray(clusters)
    known = np.isfinite(commanded).all(axis=1)
    out: dict[str, Any] = {"windows": int(known.sum()), "material": material, "gain": {}, "modes": {},
                           "responses": {}}
    selections = {0: known & (np.nan_to_num(commanded[:, 0]) > MOVING_SPEED),
                  1: known & (np.abs(np.nan_to_num(commanded[:, 1])) > TURN_THRESHOLD)}
    for name, (read, command) in RESPONSES.items():
        x, y = commanded[known, command], real[known, read]
        variance = float(((x - x.mean()) ** 2).sum())
        gain = float(((x - x.mean()) * (y - y.mean())).sum() / variance) if variance > 0 else 0.0
        out["gain"][name] = gain
        sel = selections[command]
        sign = np.sign(commanded[sel, 1]) if command == 1 else np.ones(int(sel.sum()))
        means = {mode: sign * readouts[mode][sel, read] for mode in ("real", *modes)}
        means["commanded"] = sign * commanded[sel, command]
        for mode, values in means.items():
            out["modes"].setdefault(mode, {})[name] = float(values.mean()) if sel.any() else None
        motion = EGO_MOTION_TARGETS[command]
        low_mode, high_mode = f"{motion}_x0.5", f"{motion}_x1.5"
        if len(set(clusters[sel])) < 2 or gain <= 0 or low_mode not in modes or high_mode not in modes:
            out["responses"][name] = None
            continue
        factor = modes[high_mode][command] - modes[low_mode][command]
        difference = sign * (readouts[high_mode][sel, read] - readouts[low_mode][sel, read])
        expected = gain * factor * sign * commanded[sel, command]
        iv = bootstrap_statistic(clusters[sel], lambda w, d=difference, e=expected: float(w @ d / (w @ e)), reps,
                                 seed=seed)
        out["responses"][name] = {"relative": iv.estimate, "low": iv.low, "high": iv.high,
                                  "readout_difference": float(difference.mean()),
                                  "real_difference": float(expected.mean()), "windows": int(sel.sum()),
                                  "clips": iv.clusters, "verdict": decide(iv, material)}
        if "original" in modes:
            steps = {}
            for label, upper, lower in ((f"{high_mode} - original", high_mode, "original"),
                                        (f"original - {low_mode}", "original", low_mode)):
                step = sign * (readouts[upper][sel, read] - readouts[lower][sel, read])
                part = gain * (modes[upper][command] - modes[lower][command]) * sign * commanded[sel, command]
                step_iv = bootstrap_statistic(clusters[sel], lambda w, d=step, e=part: float(w @ d / (w @ e)), reps,
                                              seed=seed)
                steps[label] = {"relative": step_iv.estimate, "low": step_iv.low, "high": step_iv.high,
                                "verdict": decide(step_iv, material)}
            out["responses"][name]["steps"] = steps
            out["responses"][name]["ordered"] = all(v["verdict"] == "used" for v in steps.values())
    return out


def clip_latents(cache: LatentCache, split: str, level: str) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Per clip of a split: normalised latents [T, ...] of ``level`` (as the predictors see them), odometry, key."""
    clips, arrays = cache.index(split).clips, cache.arrays(split)  # the clips in split order
    keys = clips["key"].tolist()
    rows = [slice(o, o + n) for o, n in zip(clips["offset"].tolist(), clips["length"].tolist())]
    return ([cache.normalize(level, arrays[level][r]).numpy() for r in rows], [arrays["odometry"][r] for r in rows],
            keys)


def latent_template(cache: LatentCache, level: str, chunk: int = 4096) -> np.ndarray:
    """The train mean per position and channel of the normalised latents (the fixed template)."""
    array, total = cache.arrays("train")[level], None
    for start in range(0, len(array), chunk):
        part = array[start:start + chunk].astype(np.float64).sum(axis=0)
        total = part if total is None else total + part
    return cache.normalize(level, total / len(array)).numpy()  # the normalisation is affine: it commutes with the mean


def latent_templates(cache: LatentCache) -> dict[str, torch.Tensor]:
    """Per latent level, the template of the dataset-mean baseline: the train latents' mean."""
    return {level: torch.from_numpy(latent_template(cache, level)) for level in KINDS}


def latent_statistics(cache: LatentCache, data: DataConfig, settings, seed: int,
                      templates: dict[str, torch.Tensor]) -> tuple[dict[str, Any], tuple[np.ndarray, ...]]:
    """Energy shares per latent set on val (about ``templates``, :func:`latent_templates`) and the ego-motion
    probe from abstract latents 0.5 s apart; also the fitted probe."""
    step = (data.detail_window - data.detail_context) * data.detail_stride
    out: dict[str, Any] = {"step_frames": step, "step_s": step / data.fps}
    for level in KINDS:
        latents, _, _ = clip_latents(cache, "val", level)
        out[level] = energy_shares(latents, templates[level].numpy(), step)
    pairs = {}
    for split in ("train", "val"):
        latents, odometry, keys = clip_latents(cache, split, "abstract")
        pairs[split] = ego_motion_pairs(latents, odometry, keys, step, settings.probe_stride, settings.strips)
    penalty, cv_r2 = select_penalty(*pairs["train"], settings.ridge, settings.probe_folds, seed)
    record, probe = ego_motion_probe(pairs["train"][:2], pairs["val"][:2], pairs["val"][2], penalty,
                                     settings.bootstrap_reps, seed)
    out["ego_motion_probe"] = {**record, "penalty": dict(zip(EGO_MOTION_TARGETS, penalty)),
                               "train_cv_r2": {name: {str(p): r for p, r in scores.items()}
                                               for name, scores in zip(EGO_MOTION_TARGETS, cv_r2)},
                               "features": f"abstract latents at t and t + {step / data.fps:g} s, "
                                           + (f"{settings.strips} vertical strips x channels" if settings.strips
                                            else "the whole latent grid")}
    return out, probe


def predictor_rows(stage: str, per_seed: list[tuple[dict, dict]], keys, threshold: float, reps: int,
                   seed: int) -> tuple[list[dict], list[dict]]:
    """One predictor's variant rows (when it has altered inputs) and baseline rows at 0.5 s and 1 s, from
    :func:`evaluate_predictor`'s results for each of ``evaluation.seeds``, averaged over the seeds."""
    errors = mean_over_seeds([p[0] for p in per_seed])
    variants = (effect_rows(stage, errors, "true", keys, threshold, reps, seed, [p[0] for p in per_seed])
                if len(errors) > 1 else [])
    ahead = {name: np.mean([p[1][name] for p in per_seed], axis=0) for name in per_seed[0][1]}
    baselines = []
    for horizon, seconds in (("0.5", 0.5), ("1", 1.0)):
        baselines += baseline_rows(
            stage, seconds, ahead[f"model_{horizon}"],
            {"repeat_last": ahead[f"repeat_{horizon}"], "dataset_mean": ahead[f"mean_{horizon}"]},
            keys, threshold, reps, seed)
    return variants, baselines


# --------------------------------------------------------------------------- report rows


def claim_verdict(low: float, high: float, threshold: float) -> str:
    """The claim reading of an interval: "holds" / "does not hold" / "not resolved at this sample size"."""
    if low > threshold:
        return "holds"
    return "does not hold" if high < threshold else "not resolved at this sample size"


def conditioning_rows(record: ConditioningRecord) -> list[dict]:
    """One table of the stage's record: per model and check, the error with the true input (or of the model),
    the alternative's error, effect = (alternative - error) / error with its interval, and the verdict. The
    steering-response rows hold instead the probe-read difference of real drives ("error") and of the model's
    latents ("alternative_error"), and their ratio as the effect."""
    rows = []
    for r in record.variants:
        if r.verdict == "reference":
            continue
        ref = next(x for x in record.variants if x.model == r.model and x.metric == r.metric
                   and x.verdict == "reference")
        rows.append({"model": r.model, "check": f"input: {r.variant}", "metric": r.metric,
                     "error": ref.error, "alternative_error": r.error, "effect": r.effect, "low": r.low,
                     "high": r.high, "verdict": r.verdict, "windows": r.windows, "clips": r.clips})
    for b in record.baselines:
        rows.append({"model": b.model, "check": f"beats {b.baseline} at {b.horizon_s:g} s",
                     "metric": "one_step_mse", "error": b.model_mse, "alternative_error": b.baseline_mse,
                     "effect": b.effect, "low": b.low, "high": b.high, "verdict": b.verdict,
                     "windows": b.windows, "clips": b.clips})
    response = record.steering_response
    for name, s in (response.responses.items() if response is not None else ()):
        if s is None:
            continue
        how = "read from the grid" if name == "sideways_shift" else "probe-read"
        rows.append({"model": response.model, "check": f"latents answer {name} x1.5 vs x0.5 ({how})",
                     "metric": f"{name}_readout", "error": s.real_difference,
                     "alternative_error": s.readout_difference, "effect": s.relative, "low": s.low,
                     "high": s.high, "verdict": s.verdict, "windows": s.windows, "clips": s.clips})
    return rows
