"""Networks built on the meta device and given memory by :func:`orbis2.models.meta.materialize`: every buffer
derived from the configuration equals an eagerly built network's, bit for bit, and nothing else holds leftover
memory. ``to_empty`` alone left the steered predictor's shift rates as garbage or NaN, by chance."""

from __future__ import annotations

import pytest
import torch

from orbis2.models.inverse_dynamics import InverseDynamicsNet
from orbis2.models.meta import materialize
from orbis2.models.sizes import stdit_config
from orbis2.models.stdit import build_stdit
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

from conftest import ROOT  # noqa: F401  (the project root on sys.path for the fixtures)

# Every network family and option that adds a module of its own (steering, its shift, the subgoal shift).
NETWORKS = {
    "abstract": lambda: build_stdit("smoke", 4, causal=True),
    "abstract_steered": lambda: build_stdit(stdit_config("smoke", steering_shift=True), 4, causal=True,
                                            steering=True),
    "detail": lambda: build_stdit("smoke", 4, causal=False, abstract_channels=3),
    "detail_subgoal": lambda: build_stdit(stdit_config("smoke", subgoal_shift=True), 4, causal=False,
                                          abstract_channels=3),
    "tokenizer_detail": lambda: build_detail_tokenizer("smoke"),
    "tokenizer_abstract": lambda: build_abstract_tokenizer("smoke", teacher_dim=8),
    "inverse_dynamics": lambda: InverseDynamicsNet(),
}


def non_persistent_buffers(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The buffers no state dict carries: what materialize must compute itself."""
    saved = set(model.state_dict())
    return {name: b for name, b in model.named_buffers() if name not in saved}


@pytest.mark.parametrize("name", NETWORKS)
def test_materialize_computes_the_derived_buffers_and_leaves_the_rest_nan(name):
    eager = NETWORKS[name]()
    with torch.device("meta"):
        meta = NETWORKS[name]()
    model = materialize(meta, "cpu")
    derived = non_persistent_buffers(eager)
    assert derived.keys() == non_persistent_buffers(model).keys()
    for key, value in derived.items():
        assert torch.equal(dict(model.named_buffers())[key], value), key
    for key, value in model.state_dict().items():  # for a load or the caller's draws: NaN until then
        assert (value.isnan() if value.is_floating_point() else value == 0).all(), key
    model.load_state_dict(eager.state_dict())
    for (key, a), b in zip(model.state_dict(keep_vars=True).items(), eager.state_dict(keep_vars=True).values()):
        assert torch.equal(a, b), key


def test_a_derived_buffer_without_reset_buffers_is_nan_not_garbage():
    """What the test above guards against: a module that derives a buffer in __init__ only."""

    class Forgetful(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.register_buffer("rates", torch.tensor([0.5, 1.0]), persistent=False)

    with torch.device("meta"):
        model = Forgetful()
    assert materialize(model, "cpu").rates.isnan().all()
    assert not non_persistent_buffers(Forgetful())["rates"].isnan().any()
