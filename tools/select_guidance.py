"""Choose the steering-guidance scale on a selection split, never on the split that reports it.

    python tools/select_guidance.py --guidance 1 2 3 [--split val] [--out reports/guidance_selection]
        [--params params.yaml] [--profile default]

Runs the `eval_steering` stage once per scale on the trained models of the workspace, with
`evaluation.steering_split` set to ``--split`` (default `val`: drives disjoint from the `turns`
drives the stage reports on) and everything else from the params file, then applies
:func:`orbis2.eval.protocols.steering.choose_guidance`: the smallest scale whose two ordering steps by
`evaluation.inverse_dynamics` (original - yaw x0.5, yaw x1.5 - original) both have a
clip-bootstrap lower bound above `evaluation.steering_turn_material_deg`. Writes each scale's
record and strip, and ``selection.json``, under ``--out``; put the chosen scale in params.yaml
(`evaluation.<profile>.steering_guidance`).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import yaml

from orbis2.config.params import load_config, load_params
from orbis2.eval.protocols.steering import choose_guidance
from orbis2.eval.records import SteeringRecord, from_json
from orbis2.io import atomic_file

STAGE = Path(__file__).resolve().parents[1] / "stages" / "eval_steering.py"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--guidance", type=float, nargs="+", required=True, help="the scales to try (1: none)")
    parser.add_argument("--split", default="val", help="the selection split (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("reports/guidance_selection"), help="(default: %(default)s)")
    parser.add_argument("--params", type=Path, default=Path("params.yaml"), help="(default: %(default)s)")
    parser.add_argument("--profile", default=None, help="(default: the params file's `profile`)")
    args = parser.parse_args()
    if any(w < 0 for w in args.guidance):
        sys.exit(f"--guidance {args.guidance}: every scale must be >= 0 (1: no guidance)")
    cfg = load_config(args.params, args.profile)
    ev = cfg.evaluation
    if args.split == ev.steering_split:
        sys.exit(f"--split {args.split} is the split eval_steering reports on; choose on another one (e.g. val)")
    args.out.mkdir(parents=True, exist_ok=True)

    records = {}
    for scale in args.guidance:
        params = load_params(args.params)
        params["evaluation"].setdefault(cfg.profile, {}).update(steering_split=args.split, steering_guidance=scale)
        scaled = args.out / f"params_g{scale:g}.yaml"
        scaled.write_text(yaml.safe_dump(params, sort_keys=False))
        record = args.out / f"steering_g{scale:g}.json"
        subprocess.run([sys.executable, str(STAGE), "--params", str(scaled), "--profile", cfg.profile,
                        "--out", str(record), "--strip", str(args.out / f"strip_g{scale:g}.png"),
                        "--no-truth"], check=True)  # the truth stage renders the reported split only
        records[scale] = from_json(SteeringRecord, record, "eval_steering")

    result = choose_guidance(records, ev.inverse_dynamics, ev.steering_turn_material_deg, args.split)
    with atomic_file(args.out / "selection.json") as tmp:
        tmp.write_text(result.text())
    for scale, record in records.items():
        steps = record.responses[ev.inverse_dynamics].turn_steps_deg or {}
        print(f"guidance {scale:g}: " + ", ".join(f"{name} {s.estimate:+.1f} [{s.low:+.1f}, {s.high:+.1f}]"
                                                  for name, s in steps.items()))
    print(f"chosen on {args.split}: {result.chosen:g} "
          f"({'both steps' if result.resolved else 'NOT both steps'} above {result.material_deg:g} deg)")


if __name__ == "__main__":
    main()
