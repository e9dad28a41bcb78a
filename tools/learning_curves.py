"""Learning curves of a predictor recipe: does it use its conditioning, and after how many samples?

    python tools/learning_curves.py detail --steps 3000 --eval-every 250 --lr 1e-3 --batch 8 \
        --out reports/learning_curves/detail.json [--profile default] [--hidden 128] [--ema 0.999]
    python tools/learning_curves.py plot reports/learning_curves/*.json --out reports/learning_curves.png

Trains one predictor stage of the registry on the existing latent cache (``data/latents``) with
the shared training loop and, every ``--eval-every`` steps, measures on fixed val windows with
the same noise draws for every variant (paired):

- ``mse_true``: latent MSE of the one-step conditional mean (one Euler step from pure noise,
  the model's estimate of E[x | context]) against the real target frames;
- ``mse_repeat``: repeating the last context frame (the trivial baseline);
- ``mse_other_subgoal`` / ``mse_no_subgoal`` (bottom predictors): the subgoal taken from a window
  of *another clip* / no conditioning at all;
- ``mse_null_steering`` / ``mse_negated_yaw`` / ``loss_*`` (steered predictors): the same with
  null steering or the yaw rate negated, in flow loss as well (the steering moves 0.5 s of motion,
  which the loss sees more directly than the one-step mean).

Each figure is a mean over windows; the JSON keeps per-clip means so intervals can be drawn
over clips. The files are what docs/learning_curves/learning_curves.png is drawn from; the chosen
budgets in params.yaml come from them (docs/pipeline.md, "How the default recipe was chosen").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from orbis2.config.params import load_config
from orbis2.eval.figures import pyplot, save_figure
from orbis2.eval.protocols.conditioning import flow_loss, one_step_mean, per_window_mse
from orbis2.hierarchy import detail_condition, rate_geometry, steering_features, window_key
from orbis2.latents import collate, open_cache
from orbis2.registry import registry
from orbis2.tasks.predictors import STAGES, PredictorTask
from orbis2.train import train


def other_clip_order(keys: list[str]) -> np.ndarray:
    """For each window, the index of a window from another clip (half-way round the split)."""
    n = len(keys)
    order = (np.arange(n) + n // 2) % n
    same = [keys[i] == keys[j] for i, j in enumerate(order)]
    if any(same):
        raise SystemExit("learning_curves: the val split has a clip holding over half of the windows; "
                         "add val clips")
    return order


class CurveTask(PredictorTask):
    """A predictor task whose evaluation is the paired conditioning diagnostics above."""

    def __init__(self, *args, windows: int, **kwargs):
        super().__init__(*args, **kwargs)
        count = min(len(self.val_set), windows)
        picks = np.linspace(0, len(self.val_set) - 1, count).round().astype(int)
        items = [self.val_set[int(i)] for i in picks]
        self.clip_of = [item["key"] for item in items]
        self.batch = collate(items)
        self.swap = other_clip_order(self.clip_of)

    @torch.no_grad()
    def evaluate(self, model, step):
        device = next(model.parameters()).device
        spec, data = self.spec, self.data
        n_context = rate_geometry(data, spec.rate)[2]
        frames = self.batch[self.batch_key].to(device)
        context, target = frames[:, :n_context], frames[:, n_context:]
        variants: dict[str, dict] = {"true": {}}
        if spec.condition is not None:
            subgoals = self.batch[window_key(spec.condition, "slow")].to(device)
            variants["true"] = dict(zip(("cond_frames", "cond_mask"), detail_condition(subgoals, data)))
            other = subgoals.clone()
            other[:, -1] = subgoals[self.swap, -1]  # only the subgoal comes from another clip
            variants["other_subgoal"] = dict(zip(("cond_frames", "cond_mask"), detail_condition(other, data)))
            none = variants["true"]["cond_mask"].clone().fill_(False)
            variants["no_subgoal"] = {"cond_frames": variants["true"]["cond_frames"] * 0, "cond_mask": none}
        if spec.steering:
            steer, unknown = steering_features(self.batch["odometry"], self.batch["has_odometry"], data,
                                              (self.cfg.speed_scale, self.cfg.yaw_rate_scale))
            steer, unknown = steer.to(device), unknown.to(device)
            negated = steer * steer.new_tensor([1.0, -1.0])
            variants["true"] = {"steering": steer, "steering_drop": unknown}
            variants["null_steering"] = {"steering": steer, "steering_drop": torch.ones_like(unknown)}
            variants["negated_yaw"] = {"steering": negated, "steering_drop": unknown}
        out = {"samples": float(step * self.cfg.train.batch_size)}
        repeat = context[:, -1:].expand_as(target)
        out["mse_repeat"] = _np(per_window_mse(repeat, target))
        out["mse_zero"] = _np(per_window_mse(torch.zeros_like(target), target))
        g = torch.Generator(device).manual_seed(1234)  # one noise draw and tau per window, shared by all variants
        eps = torch.randn(target.shape, generator=g, device=device)
        tau = torch.rand(len(target), generator=g, device=device)
        for name, cond in variants.items():
            model_fn = partial(model, frame_rate=self.frame_rate)
            out[f"mse_{name}"] = _np(per_window_mse(one_step_mean(model_fn, context, eps, **cond), target))
            out[f"loss_{name}"] = _np(flow_loss(model_fn, context, target, eps, tau, **cond))
        return {k: float(np.mean(v)) if isinstance(v, np.ndarray) else v for k, v in out.items()} | {
            f"clips/{k}": _per_clip(v, self.clip_of) for k, v in out.items() if isinstance(v, np.ndarray)}


def _np(values: torch.Tensor) -> np.ndarray:
    return values.cpu().numpy()


def _per_clip(values: np.ndarray, clips: list[str]) -> dict[str, float]:
    return {c: float(np.mean([v for v, k in zip(values, clips) if k == c])) for c in sorted(set(clips))}


def plot(paths: list[Path], out: Path) -> None:
    """One panel per curve file: every measured MSE against training samples."""
    plt = pyplot()
    runs = [json.loads(p.read_text()) | {"name": p.stem} for p in paths]
    fig, axes = plt.subplots(1, len(runs), figsize=(4.2 * len(runs), 3.4), squeeze=False)
    for ax, run in zip(axes[0], runs):
        samples = [r["samples"] for r in run["curve"]]
        for key in sorted(k for k in run["curve"][0] if k.startswith("mse_") and k != "mse_zero"):
            style = "--" if key == "mse_repeat" else "-"
            ax.plot(samples, [r[key] for r in run["curve"]], style, label=key[4:].replace("_", " "))
        t = run["train"]
        ax.set_title(f"{run['name']}: lr {t['lr']:g}, batch {t['batch_size']}", fontsize=9)
        ax.set_xlabel("training samples")
        ax.set_ylim(0, None)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("one-step latent MSE (val)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "plot":
        parser = argparse.ArgumentParser(prog="learning_curves.py plot")
        parser.add_argument("curves", type=Path, nargs="+")
        parser.add_argument("--out", type=Path, required=True)
        args = parser.parse_args(argv[1:])
        return plot(args.curves, args.out)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stage", choices=sorted(STAGES))
    parser.add_argument("--profile", default=None)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--eval-every", type=int, default=250)
    parser.add_argument("--lr", type=float, default=None)
    parser.add_argument("--batch", type=int, default=None)
    parser.add_argument("--warmup", type=int, default=None)
    parser.add_argument("--ema", type=float, default=None, help="EMA decay; 0 for none")
    parser.add_argument("--hidden", type=int, default=None)
    parser.add_argument("--windows", type=int, default=256, help="val windows per evaluation")
    parser.add_argument("--init", default=None, help="predictor.pt to start from (e.g. for action)")
    parser.add_argument("--latents", type=Path, default=None,
                        help="the latent cache (default: the stage's latent set, registry.yaml layout)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    cfg = load_config(args.params, args.profile)
    pc = cfg.section(args.stage)
    changes = {k: v for k, v in (("steps", args.steps), ("lr", args.lr), ("batch_size", args.batch),
                                 ("warmup_steps", args.warmup)) if v is not None}
    if args.ema is not None:
        changes["ema_decay"] = args.ema or None
    train_cfg = dataclasses.replace(pc.train, eval_every=args.eval_every, log_every=args.eval_every,
                                    checkpoint_every=10**9, **changes)
    model = dict(pc.model)
    if args.hidden is not None:
        model["hidden_size"] = args.hidden
    pc = dataclasses.replace(pc, train=train_cfg, model=model, init_from=None)
    cache = open_cache(args.latents or registry().latent_sets[STAGES[args.stage].latents].root)
    init = None
    if args.init:
        from orbis2.models.files import load_predictor
        init = load_predictor(Path(args.init)).model.state_dict()
    task = CurveTask(args.stage, pc, cfg.data, cache, init, windows=args.windows)
    started = time.perf_counter()
    work = args.out.with_suffix(".run")
    result = train(task, train_cfg, work)
    curve = [{"step": step, **m} for step, m in result.history if "mse_true" in m]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"stage": args.stage, "profile": cfg.profile, "train": dataclasses.asdict(train_cfg),
                                    "model": model, "windows": len(task.clip_of), "clips": len(set(task.clip_of)),
                                    "wall_seconds": time.perf_counter() - started, "curve": curve}, indent=1))
    last = curve[-1]
    print(f"[learning_curves] {args.stage}: {last['samples']:.0f} samples, " + ", ".join(
        f"{k} {v:.4f}" for k, v in last.items() if k.startswith(("mse_", "loss_"))), file=sys.stderr)


if __name__ == "__main__":
    main()
