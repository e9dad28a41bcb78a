"""Throughput of the procedural town renderer (RGB + depth + labels, no video encoding).

    python benchmarks/bench_town.py [--width 256 --height 144 --frames 300 --workers 2]

Prints frames/s on one process, frames/s with N worker processes rendering different episodes
side by side (one numba thread each), and the wall time of one full episode (simulate + render).
Town generation and JIT loading are done before the clocks start. Wall-clock rates depend on what
else runs on the machine, so the CPU time per frame and the load average are printed too.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

TOWN_SEED = 20260101
FPS = 10


def render_frames(args: tuple[int, int, int, int, mp.Barrier | None]) -> tuple[float, float, int, float]:
    """Render `frames` frames of ego episode `seed`; returns (start, end, frames, cpu seconds)."""
    width, height, frames, seed, barrier = args
    from orbis2.sim import Camera, Renderer, Town, simulate_ego

    town = Town.generate("default", TOWN_SEED)
    track = simulate_ego(town, seed, frames / FPS, FPS)
    renderer = Renderer(town, Camera(width, height))
    renderer.render(track.x[0], track.y[0], track.yaw[0], 0.0)  # JIT load / warm-up
    if barrier is not None:
        barrier.wait()
    start, cpu = time.perf_counter(), time.process_time()
    for k in range(frames):
        renderer.render(track.x[k], track.y[k], track.yaw[k], track.t[k])
    return start, time.perf_counter(), frames, time.process_time() - cpu


def _worker(args_and_queue):
    *args, queue = args_and_queue
    queue.put(render_frames(tuple(args)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=144)
    p.add_argument("--frames", type=int, default=300, help="frames per process")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--episode-seconds", type=float, default=20.0)
    a = p.parse_args()
    res = f"{a.width}x{a.height}"
    print(f"load average   : {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs before the run")

    start, end, n, cpu = render_frames((a.width, a.height, a.frames, 1, None))
    print(f"1 process      : {n / (end - start):7.1f} frames/s at {res} ({1000 * (end - start) / n:.2f} ms/frame wall, "
          f"{1000 * cpu / n:.2f} ms/frame CPU)")

    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(a.workers)
    queue = ctx.Queue()
    procs = [ctx.Process(target=_worker, args=((a.width, a.height, a.frames, 100 + i, barrier, queue),))
             for i in range(a.workers)]
    for proc in procs:
        proc.start()
    results = [queue.get() for _ in procs]
    for proc in procs:
        proc.join()
    t0 = min(r[0] for r in results)
    t1 = max(r[1] for r in results)
    total = sum(r[2] for r in results)
    cpu = sum(r[3] for r in results) / total
    print(f"{a.workers} processes    : {total / (t1 - t0):7.1f} frames/s at {res} "
          f"({total} frames, different episodes side by side; {1000 * cpu:.2f} ms CPU/frame, "
          f"{a.workers / cpu:.0f} frames/s with {a.workers} cores to ourselves)")

    from orbis2.sim import Camera, Town, render_episode, simulate_ego

    town = Town.generate("default", TOWN_SEED)
    t = time.perf_counter()
    track = simulate_ego(town, 7, a.episode_seconds, FPS)
    t_sim = time.perf_counter() - t
    frames = sum(1 for _ in render_episode(town, Camera(a.width, a.height), track))
    t_all = time.perf_counter() - t
    print(f"full episode   : {a.episode_seconds:.0f} s at {FPS} fps = {frames} frames: simulate {t_sim:.3f} s, "
          f"simulate + render {t_all:.2f} s (1 process)")
    t = time.perf_counter()
    Town.generate("heldout", TOWN_SEED + 1)
    print(f"town generate  : {time.perf_counter() - t:.2f} s (heldout style, JIT cached)")


if __name__ == "__main__":
    main()
