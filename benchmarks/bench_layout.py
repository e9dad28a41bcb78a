"""Convolution weights in contiguous (NCHW) against channels-last memory, side by side in one run.

    python benchmarks/bench_layout.py [--preset default] [--batch 8] [--json out.json]

Every convolutional network of the pipeline is built with ``orbis2.accel.conv_layout``
(channels-last weights, so channels-last activations). This times each one both ways on
the same weights and inputs (random weights: the time depends on the size only):

* ``decode``: the detail tokenizer decoding ``--batch`` latents of the preset's grid
  (the steering and FVD stages decode every generated frame);
* ``detail_train_step``: one forward and backward of the detail tokenizer and its PatchGAN
  discriminator on ``--batch`` frames (L1 plus the generator's hinge term);
* ``abstract_train_step``: the same for the abstract tokenizer's reconstruction branch;
* ``i3d``: I3D features of 4 clips of 16 frames at 224 x 224 (the FVD stages' largest cost);
* ``inverse_dynamics``: the learned instrument's CNN on ``--batch`` flow fields.

Each row gives both medians (3 runs after a warm-up, the process's torch threads), the
speed-up and the largest absolute difference of the outputs (float round-off only).
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path
from typing import Callable

import torch
from bench_fvd import median_seconds  # the same timing rule (run as a script: benchmarks/ is on the path)
from torch import nn

from orbis2.models.discriminator import build_discriminator
from orbis2.models.i3d import InceptionI3d
from orbis2.models.inverse_dynamics import IN_CHANNELS, InverseDynamicsNet
from orbis2.models.sizes import TOKENIZER_PRESETS
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

FRAME = {"smoke": (72, 128), "default": (160, 256)}  # the profiles' frame sizes (height, width)


def both_layouts(module: nn.Module) -> dict[str, nn.Module]:
    """Two copies of ``module`` with the same weights: contiguous and channels-last (3-D for 3-D convolutions)."""
    three_d = any(isinstance(m, nn.Conv3d) for m in module.modules())
    last = torch.channels_last_3d if three_d else torch.channels_last
    return {"contiguous": copy.deepcopy(module).to(memory_format=torch.contiguous_format),
            "channels_last": copy.deepcopy(module).to(memory_format=last)}


def compare(name: str, module: nn.Module, run: Callable[[nn.Module], torch.Tensor]) -> dict:
    """Median time of ``run(model)`` for each layout, the speed-up and the largest output difference."""
    models = both_layouts(module)
    outputs = {layout: run(model).detach().float() for layout, model in models.items()}
    times = {layout: median_seconds(lambda m=model: run(m)) for layout, model in models.items()}
    return {"network": name, "contiguous_s": times["contiguous"], "channels_last_s": times["channels_last"],
            "speedup": times["contiguous"] / times["channels_last"],
            "max_abs_difference": float((outputs["contiguous"] - outputs["channels_last"]).abs().max())}


def train_step(model: nn.Module, loss: Callable[[nn.Module], torch.Tensor]) -> torch.Tensor:
    model.zero_grad(set_to_none=True)
    value = loss(model)
    value.backward()
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default", choices=sorted(FRAME), help="sizes (default: %(default)s)")
    parser.add_argument("--batch", type=int, default=8, help="frames per call (default: %(default)s)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()
    torch.manual_seed(0)
    height, width = FRAME[args.preset]
    cfg = TOKENIZER_PRESETS[args.preset]
    frames = torch.rand(args.batch, 3, height, width) * 2 - 1
    detail = build_detail_tokenizer(args.preset)
    grid = detail.encode(frames[:1]).shape[-2:]
    latents = torch.randn(args.batch, cfg.latent_dim, *grid)

    class DetailGANStep(nn.Module):  # the tokenizer and its discriminator, trained together
        def __init__(self):
            super().__init__()
            self.tokenizer, self.discriminator = detail, build_discriminator(args.preset)

        def forward(self, images):
            recon, vq = self.tokenizer(images)
            return (recon - images).abs().mean() + vq.vq_loss - self.discriminator(recon).mean()

    abstract = build_abstract_tokenizer(args.preset, teacher_dim=768)
    rows = []
    with torch.no_grad():
        rows.append(compare("decode", detail.eval(), lambda m: m.decode(latents)))
        clips = torch.rand(4, 3, 16, 224, 224) * 2 - 1
        rows.append(compare("i3d", InceptionI3d().eval(), lambda m: m(clips)))
        flow = torch.randn(args.batch, IN_CHANNELS, height, width)
        rows.append(compare("inverse_dynamics", InverseDynamicsNet(32).eval(), lambda m: m(flow)))
    rows.append(compare("detail_train_step", DetailGANStep().train(), lambda m: train_step(m, lambda n: n(frames))))
    rows.append(compare("abstract_train_step", abstract.train(),
                        lambda m: train_step(m, lambda n: (n(frames)[2] - frames).abs().mean())))
    for r in rows:
        print(f"{r['network']:>20}: contiguous {r['contiguous_s']:.3f} s, channels-last {r['channels_last_s']:.3f} s "
              f"({r['speedup']:.2f}x; largest difference {r['max_abs_difference']:.1e})")
    if args.json:
        args.json.write_text(json.dumps({"threads": torch.get_num_threads(), "preset": args.preset,
                                         "batch": args.batch, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
