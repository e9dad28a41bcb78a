"""The training step's speed options: no host sync, one graph for the loss, checkpointing, loading, compile."""

import dataclasses
from collections import Counter

import pytest
import torch
from test_predictors import SPAN, tiny_cfg, write_cache
from torch.utils._python_dispatch import TorchDispatchMode

from orbis2.errors import ConfigError
from orbis2.models.stdit import build_stdit
from orbis2.tasks.predictors import PredictorTask, window_batches
from orbis2.train import DataSpec, _Env, _Meter, _Run, set_checkpointing

from conftest import train_config

aten = torch.ops.aten
SYNC_OPS = {aten._local_scalar_dense.default, aten.item.default, aten.is_nonzero.default}
# One predictor of each kind: diffusion forcing, teacher forcing, abstract-conditioned, steered, reflow.
KINDS = ("abstract_df", "abstract_tf", "detail", "action", "detail_distill")


class SyncCounter(TorchDispatchMode):
    """Counts the ops that read a tensor's value on the host, by where they ran (inside a network or not).

    ``host_counters`` are tensors that live on the host by design (the optimiser's step counts on the
    CPU, which its CUDA kernels keep on the device): reading them is no device sync.
    """

    def __init__(self, networks: list[torch.nn.Module], host_counters: list[torch.Tensor] = ()):
        super().__init__()
        self.counts: Counter = Counter()
        self.depth = 0
        self.host = {t.data_ptr() for t in host_counters}
        for net in networks:
            net.register_forward_pre_hook(self._enter)
            net.register_forward_hook(self._leave)

    def _enter(self, *_):
        self.depth += 1

    def _leave(self, *_):
        self.depth -= 1

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in SYNC_OPS and not (args and torch.is_tensor(args[0]) and args[0].data_ptr() in self.host):
            self.counts["network" if self.depth else "step"] += 1
        return func(*args, **(kwargs or {}))


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return write_cache(tmp_path_factory.mktemp("cache"), {"train": [SPAN + 3], "val": [SPAN + 5]})


def make_run(stage, cache, smoke_cfg, tmp_path, **train_changes):
    cfg = tiny_cfg(smoke_cfg, stage)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **train_changes))
    init = None
    if stage == "detail_distill":  # the teacher: an untrained detail predictor of the same build
        teacher = PredictorTask("detail", tiny_cfg(smoke_cfg, "detail"), smoke_cfg.data, cache)
        init = teacher.build_model().state_dict()
    task = PredictorTask(stage, cfg, smoke_cfg.data, cache, init)
    return task, _Run(task, cfg.train, tmp_path, None, _Env(0, 1, torch.device("cpu")))


@pytest.mark.parametrize("stage", KINDS)
def test_a_training_step_reads_nothing_on_the_host(stage, cache, smoke_cfg, tmp_path):
    """Loss, metrics, backward, clipping, optimiser and EMA of one step, and the networks' forwards (counted
    apart as "network"): no host read anywhere."""
    task, run = make_run(stage, cache, smoke_cfg, tmp_path)
    batches = iter(task.batches(DataSpec(0, 1, 4, 3, 0, 0)))
    meter = _Meter()
    run.train_step(next(batches), meter)  # the optimiser creates its state
    steps = [s["step"] for opt in run.optimizers.values() for s in opt.state.values()]
    networks = [run.model] + ([task.teacher(torch.device("cpu"))] if stage == "detail_distill" else [])
    with SyncCounter(networks, steps) as counter:
        run.train_step(next(batches), meter)
    assert counter.counts["step"] == counter.counts["network"] == 0, counter.counts
    assert set(meter.reduce(run.env)) >= {"loss", "grad_norm"}  # the meter reads the tensors when it logs


def test_the_sync_counter_sees_a_loss_read_on_the_host():
    x = torch.ones(3, requires_grad=True)
    with SyncCounter([]) as counter:
        loss = (x * 2).sum()
        loss.item()
        if loss > 0:  # a tensor in a Python condition
            loss.backward()
    assert counter.counts["step"] == 2


@pytest.mark.parametrize("stage", KINDS)
def test_the_loss_is_one_graph_around_the_network(stage, cache, smoke_cfg, tmp_path):
    """torch._dynamo.explain of the step's loss with a stand-in network: the loss code breaks no graph."""
    task, _ = make_run(stage, cache, smoke_cfg, tmp_path)
    batch = next(iter(task.batches(DataSpec(0, 1, 4, 3, 0, 0))))
    draws = task.draws(batch, torch.Generator().manual_seed(0), True)

    def network(x, tau, **cond):
        return x * tau[:, :, None, None, None] + cond["frame_rate"]

    torch._dynamo.reset()
    explained = torch._dynamo.explain(task.objective_from_draws)(network, batch, draws, True)
    assert explained.graph_break_count == 0, [r.reason for r in explained.break_reasons]
    assert explained.graph_count == 1


@pytest.mark.parametrize("stage", KINDS)
def test_the_training_forward_and_loss_are_one_graph(stage, cache, smoke_cfg, tmp_path):
    """With the stage's own network: torch._dynamo.explain finds no graph break in the forward and the loss."""
    task, _ = make_run(stage, cache, smoke_cfg, tmp_path)
    model = task.build_model().train()
    batch = next(iter(task.batches(DataSpec(0, 1, 4, 3, 0, 0))))
    draws = task.draws(batch, torch.Generator().manual_seed(0), True)
    torch._dynamo.reset()
    step = torch._dynamo.explain(task.objective_from_draws)(model, batch, draws, True)
    assert step.graph_break_count == 0, [(r.reason, r.user_stack[-1]) for r in step.break_reasons]


def grads_of(model, x, tau, cond):
    model.zero_grad(set_to_none=True)
    loss = model(x, tau, **cond).pow(2).mean()
    loss.backward()
    return loss.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]


def saved_bytes(model, x, tau, cond) -> int:
    """Bytes of the tensors autograd keeps outside checkpointed regions (one count per storage)."""
    storages = {}

    def pack(t):
        storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        model(x, tau, **cond).pow(2).mean()
    return sum(storages.values())


def test_checkpointing_policies_keep_the_gradients():
    """Full and selective checkpointing recompute exactly what they dropped: the same loss and grads, bit for bit."""
    torch.manual_seed(0)
    model = build_stdit("smoke", 4, causal=False, abstract_channels=4).train()
    torch.nn.init.normal_(model.final_layer.linear.weight, std=0.02)
    x, tau = torch.randn(2, 10, 4, 3, 4), torch.rand(2, 10)
    mask = torch.zeros(2, 10, dtype=torch.bool)
    mask[:, [4, 9]] = True
    cond = {"frame_rate": 10.0, "cond_frames": torch.randn(2, 10, 4, 3, 4), "cond_mask": mask}
    plain_loss, plain_grads = grads_of(model, x, tau, cond)
    plain_bytes = saved_bytes(model, x, tau, cond)
    for policy in ("selective", "full"):
        set_checkpointing(model, len(model.blocks), policy)
        loss, grads = grads_of(model, x, tau, cond)
        assert torch.equal(loss, plain_loss)
        assert all(torch.equal(a, b) for a, b in zip(grads, plain_grads)), policy
        assert saved_bytes(model, x, tau, cond) < plain_bytes / 4  # the blocks' tensors are the checkpoints' now
    set_checkpointing(model, 0, "selective")  # switching off restores the plain forward
    assert saved_bytes(model, x, tau, cond) == plain_bytes
    model.eval()
    with torch.no_grad():
        set_checkpointing(model, 2, "selective")
        assert torch.equal(model(x, tau, **cond), model(x, tau, **cond))


def test_bad_speed_options_are_refused():
    with pytest.raises(ConfigError, match="checkpoint_policy"):
        train_config(steps=1, batch_size=1, lr=0.1, checkpoint_policy="some")
    with pytest.raises(ConfigError, match="compile"):
        train_config(steps=1, batch_size=1, lr=0.1, compile="yes")
    with pytest.raises(ConfigError, match="does not support"):
        set_checkpointing(torch.nn.Linear(2, 2), 1, "selective")


def test_speed_options_do_not_change_the_resume_fingerprint():
    base = train_config(steps=1, batch_size=1, lr=0.1)
    fast = dataclasses.replace(base, compile=True, checkpoint_policy="selective", activation_checkpointing=2)
    assert fast.fingerprint() == base.fingerprint()


def test_worker_processes_and_pinning_give_the_same_batches(cache, smoke_cfg):
    task = PredictorTask("detail", tiny_cfg(smoke_cfg, "detail"), smoke_cfg.data, cache)
    spec = DataSpec(0, 1, 2, seed=5, start=1, num_workers=0)
    plain = window_batches(task.train_set, spec)
    loaded = window_batches(task.train_set, dataclasses.replace(spec, num_workers=2))
    for _ in range(4):
        a, b = next(plain), next(loaded)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_compile_compiles_the_trained_network_and_not_its_average(cache, smoke_cfg, tmp_path):
    """``compile: true`` compiles the training predictor by region, in place (every block; the state dict keeps
    its names); the EMA copy stays eager."""
    _, run = make_run("abstract_tf", cache, smoke_cfg, tmp_path, compile=True, ema_decay=0.9)
    assert all(block._compiled_call_impl is not None for block in run.model.blocks)
    assert all(block._compiled_call_impl is None for block in run.ema.blocks)
    assert not run.model.cuda_graphs  # training runs no CUDA graphs
    assert list(run.model.state_dict()) == list(run.ema.state_dict())
    _, plain = make_run("abstract_tf", cache, smoke_cfg, tmp_path / "plain")
    assert all(block._compiled_call_impl is None for block in plain.model.blocks)


def test_the_split_losses_draw_as_the_single_function_did():
    """Teacher forcing and diffusion forcing from their draws equal the draw-as-you-go procedure bit for bit."""
    from orbis2.flow import diffusion_forcing_loss, interpolate, teacher_forcing_loss

    def network(x, tau, **_):
        return torch.tanh(x * 1.3 + tau[:, :, None, None, None])

    context, target = torch.randn(4, 5, 3, 2, 2), torch.randn(4, 1, 3, 2, 2)
    g = torch.Generator().manual_seed(7)  # the draws of the old single function, in its order
    eps, tau = torch.randn(target.shape, generator=g), torch.rand(4, 1, generator=g)
    noised = torch.rand(4, generator=g) < 0.5
    aug = torch.randn(context.shape, generator=g) * 0.1
    dropped = torch.rand(4, generator=g) < 0.2
    ctx = torch.where(noised[:, None, None, None, None], context + aug, context)
    ctx = torch.where(dropped[:, None, None, None, None], torch.zeros_like(ctx), ctx)
    tau_ctx = torch.where(dropped[:, None], torch.ones(4, 5), torch.zeros(4, 5))
    x = torch.cat([ctx, interpolate(target, eps, tau)], 1)
    expected = torch.nn.functional.mse_loss(network(x, torch.cat([tau_ctx, tau], 1))[:, 5:], eps - target)
    loss, metrics = teacher_forcing_loss(network, context, target, torch.Generator().manual_seed(7), 0.5, 0.1, 0.2)
    assert torch.equal(loss, expected) and torch.equal(metrics["context_dropped"], dropped.float().mean())

    frames = torch.randn(2, 6, 3, 2, 2)
    g = torch.Generator().manual_seed(8)
    eps, tau = torch.randn(frames.shape, generator=g), torch.rand(2, 6, generator=g)
    expected = torch.nn.functional.mse_loss(network(interpolate(frames, eps, tau), tau), eps - frames)
    assert torch.equal(diffusion_forcing_loss(network, frames, torch.Generator().manual_seed(8))[0], expected)
