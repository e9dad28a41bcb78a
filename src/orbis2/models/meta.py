"""Networks built on the meta device (sizes without memory), then given memory on a real one.

Building at the paper's sizes on the CPU costs tens of seconds of default initialisation that a checkpoint load or
a test's own draws overwrite at once; building on the meta device costs nothing. ``Module.to_empty`` then gives
every tensor memory but no values: whatever the allocator hands out, NaN or garbage, differently from run to run.
:func:`materialize` makes that state the same every time: every tensor NaN, then the buffers that are no one's to
load (derived from the configuration, outside the state dict) computed again by their modules' ``reset_buffers``.
"""

from __future__ import annotations

import itertools

import torch
from torch import nn


@torch.no_grad()
def materialize(model: nn.Module, device: torch.device | str) -> nn.Module:
    """``model`` (built on the meta device) on ``device``, in place: derived buffers computed, the rest NaN.

    Parameters and persistent buffers are left NaN (integer ones zero) for the caller to load or draw: one it
    forgets shows as NaN outputs on every run, never as a run that passes or fails by chance. A module whose
    non-persistent buffers are derived from its configuration defines ``reset_buffers()``, which its
    ``__init__`` also calls (one source for their values).
    """
    model.to_empty(device=device)
    for tensor in itertools.chain(model.parameters(), model.buffers()):
        tensor.fill_(float("nan")) if tensor.is_floating_point() else tensor.zero_()
    for module in model.modules():
        if hasattr(module, "reset_buffers"):
            module.reset_buffers()
    return model
