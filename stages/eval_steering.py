"""Stage `eval_steering`: original and counterfactual steering ADE with visual odometry
-> reports/eval/steering.json, reports/eval/steering_strip.png, reports/eval/headline.png.

Rollouts of the hierarchical model with the steered top predictor (``action``) on
``steering_split`` starts, under each mode's scaling of the clip's own speed and yaw
rate. Each video's trajectory is recovered by ``evaluation.inverse_dynamics`` (the
learned instrument by default) and, with ``evaluation.opencv_rollouts``, by OpenCV
visual odometry (second column; always on the real videos); ADE in
metres after least-squares scale alignment to the commanded trajectory, scale-free
turn and path-length responses, and each instrument on the real videos as a sanity
check (:mod:`orbis2.eval.protocols.steering`). Two readings of the turn alone, each with the real
continuation as its calibration: the rollout's detail latents (their sideways shift, no
decoding) and the decoded frames' sideways motion (no learning). Both readings also
score a reference rollout: the bottom predictor alone, given the real subgoals (the real
abstract latents) with no steering, which tells the turn lost by the bottom level from
the turn the top's predictions lose. Where the data is the town, every mode's rollouts are also scored
against the true counterfactuals the ``truth`` stage rendered from the same starts
(:mod:`orbis2.eval.protocols.truth`): per-frame errors by horizon, FVD against the true videos, the
instrument's reading of the truth (its calibration) and whether each rollout is closer to the truth
under its own command than under the others. The headline figure (the README's, through the report) shows the
first clip: its real frames, the tokenizer's reconstruction of them, and the model's rollouts under the recorded
command and the yaw-rate counterfactuals, each beside the town's truth where there is one.
"""

from pathlib import Path
from typing import Any

import numpy as np

from orbis2.accel import default_device
from orbis2.assets import ensure_asset
from orbis2.data.shards import split_clips
from orbis2.data.truth import read_manifest
from orbis2.errors import OrbisError
from orbis2.eval.metrics.fvd import clip_features
from orbis2.eval.metrics.inverse_dynamics import WEIGHTS_FILE
from orbis2.eval.metrics.odometry import camera_intrinsics, get_inverse_dynamics
from orbis2.eval.protocols.steering import (
    image_turns,
    latent_turns,
    mode_record,
    odometry_sanity,
    real_videos,
    save_headline,
    save_strip,
    score_videos,
    steering_inputs,
    steering_responses,
    turn_record,
)
from orbis2.eval.protocols.systems import (
    SYSTEMS,
    cache_latents,
    eval_samples,
    generate,
    generated_indices,
    inference_settings,
    load_system,
    real_subgoals,
    rollout_steps,
    sample_clusters,
)
from orbis2.eval.protocols.truth import TruthScorer
from orbis2.eval.records import Material, Nfe, SteeringRecord, write_record
from orbis2.interfaces import INTERFACES
from orbis2.kinematics import integrate_controls
from orbis2.latents import open_cache
from orbis2.models.i3d import load_i3d
from orbis2.registry import registry
from orbis2.stage import (
    latent_paths,
    open_stage,
    predictor_files,
    stage_parser,
)

# The hierarchy with the steered top predictor (registry.yaml's `steering: true`) cascaded into its bottom one,
# on the compressed latents.
SYSTEM, TOP = "hierarchical", registry().steered
LATENT_SET = "compressed"
# The steering modes the headline figure shows (evaluation.steering_modes' names), with their row labels.
HEADLINE_MODES = {"original": "recorded command", "yaw_rate_x0.5": "yaw rate x0.5", "yaw_rate_x1.5": "yaw rate x1.5"}


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["eval_steering"], __doc__)
    parser.add_argument("--no-truth", action="store_true",
                        help="leave out the scoring against the true counterfactuals (a split the truth stage did "
                             "not render, e.g. tools/select_guidance.py's)")
    args = parser.parse_args(argv)
    with open_stage("eval_steering", args, INTERFACES["eval_steering"]) as stage:
        cfg, run = stage.cfg, stage.run
        ev, data = cfg.evaluation, cfg.data
        if data.detail_stride != 1:
            raise OrbisError(f"data.{cfg.profile}: the steering evaluation compares odometry at the video rate and "
                             f"needs fps == detail_hz (got {data.fps} and {data.detail_hz})")
        dev = default_device()
        latents = latent_paths(args, LATENT_SET)
        predictors = predictor_files(args, [SYSTEMS[SYSTEM].bottom, TOP])
        system = load_system(SYSTEM, predictors, latents.tokenizers, dev, top_override=TOP,
                             inference=inference_settings(ev))
        steer_meta = system.top.meta.get("steering")
        if steer_meta is None:
            raise OrbisError(f"{predictors[TOP]} is not steered; re-run the `{TOP}` stage")

        cache = open_cache(latents.root)
        steps = rollout_steps(data, ev.steering_seconds)
        split = ev.steering_split
        samples = eval_samples(cache, split, data, steps, ev.steering_starts_per_clip)
        clusters = sample_clusters(cache, split, samples)
        indices = [generated_indices(data, s.context_end, steps) for s in samples]
        odometry = cache.arrays(split)["odometry"]
        K = camera_intrinsics(data.width, data.height, cfg.town.hfov_deg)
        instruments = {name: get_inverse_dynamics(name, args.inverse_dynamics / WEIGHTS_FILE)
                       for name in dict.fromkeys([ev.inverse_dynamics, "opencv"])}
        on_rollouts = instruments if ev.opencv_rollouts else {ev.inverse_dynamics: instruments[ev.inverse_dynamics]}
        truth = None
        if not args.no_truth and read_manifest(args.truth)["available"]:  # the town: true counterfactuals
            i3d_file = ensure_asset("i3d_kinetics400", args.assets or Path(cfg.assets.dir),
                                    cfg.assets.local.get("i3d_kinetics400"), download=False)
            i3d = load_i3d(i3d_file).to(dev).eval()
            instrument = instruments[ev.inverse_dynamics]
            truth = TruthScorer(args.truth, samples, clusters, data, ev, steps, system.tokenizers["detail"], cache,
                                features=lambda videos: clip_features(videos, i3d, ev.batch_size, dev),
                                read_turns=lambda videos, controls: score_videos(videos, controls, instrument, K,
                                                                                 data.detail_hz),
                                instrument=ev.inverse_dynamics)
        first = cache_latents(cache, split, "detail", samples, [np.array([s.context_end]) for s in samples])
        first_frames = system.decode(first)  # [N, 1, H, W, 3]

        modes: dict[str, Any] = {}
        latent_turn: dict[str, dict[str, np.ndarray]] = {}
        image_turn: dict[str, dict[str, np.ndarray]] = {}
        real = cache_latents(cache, split, "detail", samples, indices)
        real_controls, _ = steering_inputs(samples, odometry, data, steps, 1.0, 1.0, steer_meta["scale"])
        latent_turn["real"] = latent_turns(first, real, real_controls, data.detail_hz, cfg.town.hfov_deg)
        real_frames = real_videos(split_clips(args.shards, split), samples, indices)
        image_turn["real"] = image_turns(real_frames, real_controls, data.detail_hz, cfg.town.hfov_deg)
        # Reference: the bottom level alone, given the real subgoals (no steering): the turn it can carry.
        given = generate(system, cache, split, samples, steps, data, ev, dev, desc="real subgoals",
                         subgoals=real_subgoals(system, cache, split, data, samples, steps))
        latent_turn["real_subgoals"] = latent_turns(first, given, real_controls, data.detail_hz, cfg.town.hfov_deg)
        image_turn["real_subgoals"] = image_turns(np.concatenate([first_frames, system.decode(given)], axis=1),
                                                  real_controls, data.detail_hz, cfg.town.hfov_deg)
        per_sample: dict[str, dict[str, dict[str, np.ndarray]]] = {}
        strip = {}
        headline = {"real": real_frames[0],
                    "tokenizer\n(real, encoded, decoded)": np.concatenate([first_frames[0],
                                                                            system.decode(real[:1])[0]])}
        for mode, (speed_scale, yaw_scale) in ev.steering_modes.items():
            controls, steering = steering_inputs(samples, odometry, data, steps, speed_scale, yaw_scale,
                                                 steer_meta["scale"])
            latents = generate(system, cache, split, samples, steps, data, ev, dev, steering, desc=mode)
            videos = np.concatenate([first_frames, system.decode(latents)], axis=1)
            per_sample[mode] = {name: score_videos(videos, controls, inverse, K, data.detail_hz)
                                for name, inverse in on_rollouts.items()}
            latent_turn[mode] = latent_turns(first, latents, controls, data.detail_hz, cfg.town.hfov_deg)
            image_turn[mode] = image_turns(videos, controls, data.detail_hz, cfg.town.hfov_deg)
            modes[mode] = mode_record(per_sample[mode], clusters, speed_scale, yaw_scale, ev.seed)
            if truth is not None:
                truth.add(mode, latents, videos)
            if mode in HEADLINE_MODES:
                headline[f"model:\n{HEADLINE_MODES[mode]}"] = videos[0]
                if truth is not None and mode != "original":  # the recorded command's truth is the real row
                    headline[f"town's truth:\n{HEADLINE_MODES[mode]}"] = truth.first_video[mode]
            sp, yw = controls[0]
            strip[mode] = (videos[0], integrate_controls(sp[:videos.shape[1] - 1], yw[:videos.shape[1] - 1],
                                                         1.0 / data.detail_hz))
        sanity = {name: odometry_sanity(real_frames, samples, indices, odometry, K, inverse, data, clusters, ev.seed)
                  for name, inverse in instruments.items()}

        record = SteeringRecord(
            split=split, seconds=ev.steering_seconds, samples=len(samples), clips=len(set(clusters)), seed=ev.seed,
            inverse_dynamics=ev.inverse_dynamics, instruments=list(on_rollouts),
            nfe=Nfe(top=ev.top_nfe, bottom=ev.bottom_nfe), modes=modes,
            responses={name: steering_responses(per_sample, name, clusters, ev.seed) for name in on_rollouts},
            material=Material(turn_deg=ev.steering_turn_material_deg, path_ratio=ev.steering_path_ratio_material),
            odometry_sanity=sanity[ev.inverse_dynamics], sanity=sanity,
            latent_turn=turn_record(latent_turn, clusters, ev.seed),
            image_turn=turn_record(image_turn, clusters, ev.seed),
            truth=truth.record() if truth is not None else None)
        write_record(args.out, record)
        run.log_artifact(args.out)
        save_strip(strip, data.detail_hz, args.strip)
        save_headline(headline, data.detail_hz, args.headline)
        run.log_artifact(args.headline)
        run.log_artifact(args.strip)
        run.publish(args.strip, "figures")
        run.log_metrics({f"ade_{m}": v.ade for m, v in record.modes.items()})
        if record.truth is not None:
            run.log_metrics({f"truth_fvd_{m}": v.fvd.fvd for m, v in record.truth.modes.items()})
            run.log_metrics({f"truth_instrument_turn_deg_{m}": v.instrument.turn_deg.estimate
                             for m, v in record.truth.modes.items()})
        readings = (("latent_turn", record.latent_turn), ("image_turn", record.image_turn))
        run.log_metrics({f"{reading}_deg_{m}": v.turn_deg for reading, turns in readings
                         for m, v in turns.modes.items()})

        response, floor = record.responses[ev.inverse_dynamics], record.odometry_sanity
        turn = f"{response.turn_response_deg.estimate:.1f}" if response.turn_response_deg else "n/a"
        ratio = f"{response.path_ratio.estimate:.2f}" if response.path_ratio else "n/a"
        stage.summary = ("ADE (turn) " + ", ".join(f"{m} {v.ade:.2f} m ({v.turn_deg:.0f} deg)"
                                                   for m, v in record.modes.items())
                         + f" (n={len(samples)}, {ev.inverse_dynamics}); turn response {turn} deg, path ratio "
                           f"x1.5/x0.5 {ratio}; real video ADE {floor.real_ade:.2f} m, "
                           f"shuffled {floor.shuffled_ade:.2f} m; turn read from the latents "
                           + ", ".join(f"{m} {v.turn_deg:.0f}" for m, v in record.latent_turn.modes.items())
                           + " deg; from the image motion "
                           + ", ".join(f"{m} {v.turn_deg:.0f}" for m, v in record.image_turn.modes.items())
                           + " deg" + (truth_summary(record) if record.truth is not None else ""))


def truth_summary(record: SteeringRecord) -> str:
    """The summary's words on the truth: the claim's verdict and the instrument's reading of the true turns."""
    truth = record.truth
    readings = ", ".join(f"{m} {v.instrument.turn_deg.estimate:.0f}/{v.instrument.commanded_turn_deg:.0f}"
                         for m, v in truth.modes.items())
    return (f"; against the truth: closer to its own command's truth {truth.claim.verdict}; instrument on the true "
            f"videos (read/commanded deg) {readings}")


if __name__ == "__main__":
    main()
