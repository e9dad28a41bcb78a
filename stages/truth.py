"""Stage `truth`: the town re-renders every steering start under each steering mode -> data/truth, reports/truth.json.

The starts are the steering evaluation's (``evaluation.steering_split``, ``steering_seconds``,
``steering_starts_per_clip``), the commands its modes (``evaluation.steering_modes``: the clip's own
speed and yaw rate from its last context frame on, each scaled). For each, the episode the clip was
cut from is rendered again along the commanded path (:mod:`orbis2.data.truth`): the true view the
generated counterfactual is scored against (``eval_steering``). A source other than the town has no
truth: the stage writes a manifest that says so. The report gives what was rendered, how often a
command ran into traffic or off the road, and the cost per clip and command.

    python stages/truth.py --profile smoke
"""

import os
import time
from concurrent.futures import ProcessPoolExecutor

from tqdm import tqdm

from orbis2.data.shards import load_manifest, split_clips
from orbis2.data.truth import Command, render_commands, single_thread_renderer, write_truth, write_unavailable
from orbis2.eval.protocols.starts import commanded_steps, rollout_steps, sample_ends
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, write_json
from orbis2.stage import open_stage, stage_parser


def _render(job):
    """One clip's commands, and the seconds they took on this process."""
    began = time.perf_counter()
    rendered = render_commands(*job)
    return rendered, time.perf_counter() - began


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["truth"], __doc__)
    args = parser.parse_args(argv)
    with open_stage("truth", args, INTERFACES["truth"]) as stage:
        cfg, run = stage.cfg, stage.run
        ev, data = cfg.evaluation, cfg.data
        split, modes = ev.steering_split, ev.steering_modes
        steps = commanded_steps(data, rollout_steps(data, ev.steering_seconds))
        header = {"split": split, "seconds": ev.steering_seconds, "commanded_steps": steps, "fps": data.fps,
                  "modes": modes, "width": data.width, "height": data.height}
        source = load_manifest(args.shards)["source"]
        began = time.perf_counter()
        if source != "town":
            with atomic_dir(args.out) as tmp:
                write_unavailable(tmp, {**header, "source": source},
                                             f"the {source} source has no simulator to render counterfactuals")
            stage.summary = f"no truth: the data source is {source}, not the town"
            write_json(args.report, {"available": False, "source": source})
            return
        clips = split_clips(args.shards, split)
        jobs = []
        for key in sorted(clips):
            commands = [Command(key, end, mode, float(scales[0]), float(scales[1]))
                        for end in sample_ends(len(clips[key]), data, rollout_steps(data, ev.steering_seconds),
                                               ev.steering_starts_per_clip) for mode, scales in modes.items()]
            if commands:
                jobs.append((clips[key], commands, steps, data, cfg.town, cfg.shards.jpeg_quality))
        workers = min(cfg.truth.workers or os.cpu_count() or 1, max(len(jobs), 1))
        seconds = []

        def rendered():
            with ProcessPoolExecutor(workers, initializer=single_thread_renderer) as pool:
                for items, took in tqdm(pool.map(_render, jobs), total=len(jobs), desc="truth: clips", unit="clip"):
                    seconds.append(took)
                    yield from items

        with atomic_dir(args.out) as tmp:
            manifest = write_truth(tmp, rendered(), {**header, "source": source}, cfg.shards.max_shard_mb)
        wall = time.perf_counter() - began
        commands = manifest["samples"]
        cost = {"available": True, "clips": len(jobs), "commands": commands, "frames": commands * (steps + 1),
                "workers": workers, "wall_seconds": wall,
                # One process's time per start and command (a mode's frames, rendered and encoded).
                "seconds_per_command": sum(seconds) / max(commands, 1), "events": manifest["events"]}
        write_json(args.report, cost)
        run.log_artifact(args.report)
        run.log_metrics({"commands": commands, "seconds_per_command": cost["seconds_per_command"],
                         "wall_seconds": wall,
                         **{f"{mode}_{event}": counts[event] for mode, counts in manifest["events"].items()
                            for event in ("collision", "off_road")}})
        events = ", ".join(f"{mode} {c['collision']}/{c['off_road']}" for mode, c in manifest["events"].items())
        stage.summary = (f"{commands} starts x commands of {split} ({len(jobs)} clips, {steps + 1} frames each), "
                         f"{cost['seconds_per_command']:.2f} s per command on one process, {wall:.0f} s wall on "
                         f"{workers} workers; collisions / off road per mode: {events}")


if __name__ == "__main__":
    main()
