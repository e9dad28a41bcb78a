"""Cost of the town's true counterfactuals: per clip and command (the truth stage) and per step (a live caller).

    python benchmarks/bench_truth.py [--width 256 --height 160 --seconds 6 --starts 4]

On one process, side by side in one run: the recorded frames of a window rendered as the town stage
renders them (``render_episode``), the same window re-rendered under each steering mode of params.yaml
(``render_path``: what the truth stage does per start and command, JPEG encoding included), and the
step-wise API (``PathRenderer.step``, one 0.5-s step of 5 commands at a time) against the 10 frames/s an
interactive demo needs. Prints seconds per command, frames/s and their ratio to the recorded rendering.
Town generation and JIT loading happen before the clocks start; run it on an idle machine (the load
average is printed).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

TOWN_SEED = 20260101
FPS = 10


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=160)
    p.add_argument("--seconds", type=float, default=6.0, help="commanded seconds per start (steering_seconds)")
    p.add_argument("--starts", type=int, default=4, help="episodes (one start each) timed")
    a = p.parse_args()

    import cv2
    import numpy as np

    from orbis2.config.params import load_config
    from orbis2.sim import Camera, Town, render_episode, simulate_ego
    from orbis2.sim.counterfactual import PathRenderer, render_path

    modes = load_config().evaluation.steering_modes
    town = Town.generate("default", TOWN_SEED)
    camera = Camera(a.width, a.height)
    steps = round(a.seconds * FPS)
    start = 20
    tracks = [simulate_ego(town, seed, (start + steps + 1) / FPS + 1.0, FPS) for seed in range(a.starts)]
    list(render_episode(town, camera, tracks[0]))  # JIT load
    print(f"load average   : {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs before the run")

    began = time.perf_counter()
    for track in tracks:
        for k, _ in enumerate(render_episode(town, camera, track)):
            if k == start + steps:
                break
    recorded = (time.perf_counter() - began) / (a.starts * (start + steps + 1))

    encode = [int(cv2.IMWRITE_JPEG_QUALITY), 95]
    began = time.perf_counter()
    for track in tracks:
        for speed_scale, yaw_scale in modes.values():
            path = render_path(town, camera, track, start, track.speed[start:start + steps] * speed_scale,
                               track.yaw_rate[start:start + steps] * yaw_scale)
            for frame in path.rgb:
                cv2.imencode(".jpg", frame, encode)
    per_command = (time.perf_counter() - began) / (a.starts * len(modes))

    began = time.perf_counter()
    for track in tracks:
        renderer = PathRenderer(town, camera, track, start)
        renderer.first()
        for i in range(0, steps, 5):
            renderer.step(track.speed[start + i:start + i + 5], -np.abs(track.yaw_rate[start + i:start + i + 5]))
    stepwise = (time.perf_counter() - began) / (a.starts * (steps + 1))

    res = f"{a.width}x{a.height}"
    print(f"recorded       : {1 / recorded:7.1f} frames/s at {res} (render_episode)")
    print(f"truth          : {per_command:7.3f} s per start and command ({steps + 1} frames, JPEG included): "
          f"{(steps + 1) / per_command:.1f} frames/s, {recorded * (steps + 1) / per_command:.2f}x the recorded rate")
    print(f"step-wise      : {1 / stepwise:7.1f} frames/s in 0.5-s steps: a step of 5 frames takes "
          f"{5000 * stepwise:.0f} ms of the 500 ms a caller at 10 frames/s has")
    print(f"a split        : {len(modes)} commands per start: {len(modes) * per_command:.2f} s per clip and start on "
          f"one process")


if __name__ == "__main__":
    main()
