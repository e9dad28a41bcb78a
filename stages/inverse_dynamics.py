"""Stage `inverse_dynamics`: the learned instrument that reads speed and yaw rate from consecutive frames
-> data/inverse_dynamics/model.pt (with curves/), reports/inverse_dynamics.json.

Trains on the train split's frame pairs, and on those of train clips the town drives again along
counterfactual paths (``counterfactual_clips``, ``counterfactual_scales``: the turns and off-road views
the steering evaluation's commands lead to), with the shared loop; checkpoints live in
data/runs/ (see `work_dir`): a killed run resumes there. Val R^2 on real
pairs, on the detail tokenizer's reconstructions of them and on shuffled pairs
(the control); see :mod:`orbis2.eval.metrics.inverse_dynamics`.
"""


import os

from orbis2.accel import default_device
from orbis2.eval.metrics.inverse_dynamics import (
    WEIGHTS_FILE,
    ClipFrames,
    evaluate_instrument,
    load_clips,
    pair_index,
    reconstruct,
)
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, write_json
from orbis2.stage import TOKENIZER_FILE, copy_curves, open_stage, stage_parser, work_dir
from orbis2.tasks.instrument import counterfactual_train_clips, train_instrument

INTERFACE = INTERFACES["inverse_dynamics"]
SECTIONS = INTERFACE.sections_with()


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)
    args = parser.parse_args(argv)
    with open_stage("inverse_dynamics", args, INTERFACE) as stage:
        cfg, run = stage.cfg, stage.run
        ic, fps, dev = cfg.inverse_dynamics, float(cfg.data.fps), default_device()

        work = work_dir("inverse_dynamics", cfg, SECTIONS, {"shards": args.shards / "manifest.json"}, __file__)
        recorded = load_clips(args.shards, "train", ic.scale, ic.max_train_clips)
        driven, counterfactual = counterfactual_train_clips(args.shards, cfg, cfg.truth.workers or os.cpu_count() or 1)
        train = ClipFrames(recorded.frames + driven.frames, recorded.odometry + driven.odometry,
                           recorded.keys + driven.keys)
        instrument = train_instrument(train, ic, fps, work, dev, run)
        val = load_clips(args.shards, "val", ic.scale)
        reconstructed = reconstruct(args.tokenizer / TOKENIZER_FILE, args.shards, "val", val, ic.scale, dev)
        result = evaluate_instrument(instrument, val, ic.eval_pairs, ic.train.seed, reconstructed)

        record = {"train_clips": len(recorded.keys), "train_pairs": len(pair_index(recorded)),
                  "counterfactual": counterfactual, "steps": ic.train.steps,
                  "fps": fps, "input": list(train.frames[0].shape[1:3]), "seed": ic.train.seed, "val": result}
        with atomic_dir(args.out) as tmp:
            instrument.save(tmp / WEIGHTS_FILE, record)
            copy_curves(work, tmp, "inverse_dynamics")
        write_json(args.report, record)
        run.log_artifact(args.report)
        scores = {f"val_{kind}_{k}": v for kind in ("real", "reconstructed", "shuffled")
                  for k, v in result[kind].items() if v is not None}
        run.log_metrics(scores, step=ic.train.steps)
        run.log_model(args.out, scores)  # the steering evaluation's instrument

        def pair(kind: str) -> str:
            return " / ".join("undefined" if result[kind][k] is None else f"{result[kind][k]:.2f}"
                              for k in ("speed_r2", "yaw_rate_r2"))

        stage.summary = (f"val R^2 speed / yaw rate: real {pair('real')}, reconstructed {pair('reconstructed')}, "
                         f"shuffled control {pair('shuffled')} ({result['pairs']} pairs; undefined: no variance in "
                         f"the val targets)")


if __name__ == "__main__":
    main()
