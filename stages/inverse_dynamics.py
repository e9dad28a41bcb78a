"""Stage `inverse_dynamics`: the learned instrument that reads speed and yaw rate from consecutive frames
-> data/inverse_dynamics/model.pt, reports/inverse_dynamics.json.

Trains on the train split's frame pairs; val R^2 on real pairs, on the detail
tokenizer's reconstructions of them and on shuffled pairs (the control); see
:mod:`orbis2.eval.inverse_dynamics`.
"""

from orbis2.accel import default_device
from orbis2.eval.inverse_dynamics import evaluate_instrument, load_clips, pair_index, reconstruct, train_instrument
from orbis2.io import atomic_dir, write_json
from orbis2.registry import layout_path
from orbis2.stage import open_stage, stage_parser

OUT = layout_path("inverse_dynamics")
REPORT = layout_path("report", "inverse_dynamics")
SHARDS = layout_path("shards")
DETAIL_TOKENIZER = layout_path("tokenizer", "detail") / "tokenizer.pt"


def main(argv: list[str] | None = None) -> None:
    args = stage_parser("inverse_dynamics.py", __doc__).parse_args(argv)
    with open_stage("inverse_dynamics", args, ["data", "inverse_dynamics"]) as stage:
        cfg, run = stage.cfg, stage.run
        ic, fps, dev = cfg.inverse_dynamics, float(cfg.data.fps), default_device()

        train = load_clips(SHARDS, "train", ic.scale, ic.max_train_clips)
        instrument = train_instrument(train, ic, fps, dev,
                                      log=lambda step, loss: run.log_metrics({"train_loss": loss}, step=step))
        val = load_clips(SHARDS, "val", ic.scale)
        reconstructed = reconstruct(DETAIL_TOKENIZER, SHARDS, "val", val, ic.scale, dev)
        result = evaluate_instrument(instrument, val, ic.eval_pairs, ic.seed, reconstructed)

        record = {"train_clips": len(train.keys), "train_pairs": len(pair_index(train)), "steps": ic.steps,
                  "fps": fps, "input": list(train.frames[0].shape[1:3]), "seed": ic.seed, "val": result}
        with atomic_dir(OUT) as tmp:
            instrument.save(tmp / "model.pt", record)
        write_json(REPORT, record)
        run.log_artifact(REPORT)
        run.log_metrics({f"val_{kind}_{k}": v for kind in ("real", "reconstructed", "shuffled")
                         for k, v in result[kind].items() if v is not None})

        def pair(kind: str) -> str:
            return " / ".join("undefined" if result[kind][k] is None else f"{result[kind][k]:.2f}"
                              for k in ("speed_r2", "yaw_rate_r2"))

        stage.summary = (f"val R^2 speed / yaw rate: real {pair('real')}, reconstructed {pair('reconstructed')}, "
                         f"shuffled control {pair('shuffled')} ({result['pairs']} pairs; undefined: no variance in "
                         f"the val targets)")


if __name__ == "__main__":
    main()
