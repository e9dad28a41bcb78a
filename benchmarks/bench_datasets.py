"""Time each dataset reader converting 1,000 frames into the import layout.

    python benchmarks/bench_datasets.py [--frames 1000] [--width 640] [--height 360] [--json out.json]

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

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_datasets import bdd_tree, nuplan_tree, opendv_tree, physicalai_tree  # noqa: E402

from orbis2.data.datasets import bdd100k, nuplan, opendv, physicalai_av  # noqa: E402


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
        meta = opendv_tree(root / "opendv", n_frames=n // 2, size=size)  # two videos of n / 2 frames
        runs = {
            "nuplan": lambda: nuplan.convert(db, root / "nuplan" / "sensor_blobs", root / "out1", "val",
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
    if args.json:
        args.json.write_text(json.dumps({"frames": n, "width": args.width, "height": args.height,
                                         "seconds": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
