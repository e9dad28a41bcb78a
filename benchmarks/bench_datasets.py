"""Time each dataset reader converting 1,000 frames into the import layout, and decoding AV1 and HEVC
(through PyAV) against H.264 (through OpenCV) at the same size.

    python benchmarks/bench_datasets.py [--frames 1000] [--width 640] [--height 360] [--json out.json]

The decode target: AV1 or HEVC at most 2x OpenCV's time on H.264 of the same frames. All three
are encoded here with PyAV's FFmpeg (libsvtav1, libx265, libx264) from the same frames of a
textured pattern drifting sideways (random pixels would make every codec's work meaningless),
then read with :func:`orbis2.data.video.read_video` (OpenCV for H.264 and HEVC; OpenCV decodes
no AV1, so that file goes through PyAV), and HEVC once more forced through PyAV. Timings are
only meaningful on an idle machine.

The trees are those of tests/test_datasets.py (each dataset's published layout, a known
drive in its poses), scaled to ``--frames`` frames of random pixels at ``--width`` x
``--height``: nuPlan's as JPEGs at 10 Hz (decoded and encoded into an mp4), PhysicalAI-AV's
as a 30-fps mp4 in a chunk zip (copied out), BDD100K's as a 30-fps .mov (linked) and
OpenDV-YouTube's as a 10-fps mp4 (decoded and re-encoded without its discarded ends).
Only the conversion is timed, not building the tree.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_datasets import bdd_tree, encode, nuplan_tree, opendv_tree, physicalai_tree  # noqa: E402

from orbis2.data import video  # noqa: E402
from orbis2.data.datasets import bdd100k, nuplan, opendv, physicalai_av  # noqa: E402

from conftest import moving_pattern  # noqa: E402


def decode_times(root: Path, n: int, size: tuple[int, int]) -> dict[str, float]:
    """Seconds to decode ``n`` frames of the same pictures coded as H.264, HEVC and AV1."""
    images = moving_pattern(n, size[1], size[0]) if n <= size[1] else np.concatenate(
        [moving_pattern(size[1], size[1], size[0])] * (n // size[1] + 1))[:n]
    files = {name: encode(root / f"{name}.mp4", images, 30, codec) for name, codec in
             (("h264", "libx264"), ("hevc", "libx265"), ("av1", "libsvtav1"))}
    runs = {
        "decode h264 (opencv)": lambda: video.read_video(files["h264"]),
        "decode hevc (opencv)": lambda: video.read_video(files["hevc"]),
        "decode hevc (pyav)": lambda: list(video._pyav_frames(files["hevc"])),
        "decode av1 (pyav)": lambda: video.read_video(files["av1"]),
    }
    times = {}
    for name, run in runs.items():
        start = time.perf_counter()
        decoded = len(run())
        times[name] = time.perf_counter() - start
        assert decoded == n, (name, decoded)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    size, n = (args.height, args.width), args.frames
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        db = nuplan_tree(root / "nuplan", seconds=n / 10, size=size)
        pai = physicalai_tree(root / "pai", n_frames=n, size=size)
        bdd = bdd_tree(root / "bdd", n_frames=n, size=size)
        meta = opendv_tree(root / "opendv", n_frames=n // 2, size=size)  # two videos of n / 2 frames (mp4, AV1)
        runs = {
            "nuplan": lambda: nuplan.convert(db, [root / "nuplan" / "sensor_blobs"], root / "out1", "val",
                                             clip_seconds=n / 10),
            "physicalai-av": lambda: physicalai_av.convert(pai, root / "out2"),
            "bdd100k": lambda: bdd100k.convert(bdd, root / "out3"),
            "opendv": lambda: opendv.convert(meta, root / "opendv" / "videos", root / "out4"),
        }
        for name, run in runs.items():
            start = time.perf_counter()
            run()
            results[name] = time.perf_counter() - start
            print(f"{name:<14} {n} frames at {args.width}x{args.height}: {results[name]:.2f} s")
        for name, seconds in decode_times(root / "codecs", n, size).items():
            results[name] = seconds
            print(f"{name:<22} {n} frames at {args.width}x{args.height}: {seconds:.2f} s")
        for codec in ("hevc (opencv)", "av1 (pyav)"):
            print(f"{codec} / h264 (opencv): {results[f'decode {codec}'] / results['decode h264 (opencv)']:.2f}x "
                  f"(target: at most 2x)")
    if args.json:
        args.json.write_text(json.dumps({"frames": n, "width": args.width, "height": args.height,
                                         "seconds": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
