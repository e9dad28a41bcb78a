"""Flow matching (paper eq. 1 and 2): interpolant, losses, Euler sampler, noise-level draws."""

from __future__ import annotations

import pytest
import torch

from orbis2.flow import (
    NULL_CONTEXT_TAU,
    diffusion_forcing_loss,
    euler_sample,
    interpolate,
    teacher_forcing_loss,
    velocity_target,
)


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


class Spy:
    """A model_fn that records its inputs and returns a fixed velocity."""

    def __init__(self, velocity=None):
        self.calls = []
        self.velocity = velocity

    def __call__(self, x, tau, **cond):
        self.calls.append((x.clone(), tau.clone(), cond))
        return torch.zeros_like(x) if self.velocity is None else self.velocity(x, tau)


def oracle(clean: torch.Tensor):
    """The exact velocity eps - x, recovered from x_tau and the known clean frames."""

    def velocity(x, tau):
        t = tau.reshape(*tau.shape, 1, 1, 1)
        return torch.where(t > 0, (x - clean) / t.clamp_min(1e-12), torch.zeros_like(x))

    return velocity


def test_interpolant_endpoints_and_target():
    x, eps = torch.randn(2, 3, 4, 5, 6, generator=gen(1)), torch.randn(2, 3, 4, 5, 6, generator=gen(2))
    assert torch.equal(interpolate(x, eps, torch.zeros(2, 3)), x)
    assert torch.equal(interpolate(x, eps, torch.ones(2, 3)), eps)
    tau = torch.tensor([[0.0, 0.5, 1.0], [1.0, 0.25, 0.0]])
    mixed = interpolate(x, eps, tau)
    assert torch.equal(mixed[0, 0], x[0, 0]) and torch.equal(mixed[1, 0], eps[1, 0])
    torch.testing.assert_close(mixed[1, 1], 0.75 * x[1, 1] + 0.25 * eps[1, 1])
    assert torch.equal(velocity_target(x, eps), eps - x)


def test_teacher_forcing_loss_is_zero_for_the_exact_velocity_and_packs_context_at_tau0():
    context = torch.randn(64, 3, 2, 4, 4, generator=gen(1), dtype=torch.float64)
    target = torch.randn(64, 2, 2, 4, 4, generator=gen(2), dtype=torch.float64)
    spy = Spy(oracle(torch.cat([context, target], dim=1)))
    loss, metrics = teacher_forcing_loss(spy, context, target, gen(3), frame_rate=2.0)
    assert loss.item() < 1e-20 and metrics["loss"] == loss.item()
    x, tau, cond = spy.calls[0]
    assert cond == {"frame_rate": 2.0}
    assert torch.equal(x[:, :3], context) and torch.all(tau[:, :3] == 0)
    assert torch.all(tau[:, 3] == tau[:, 4])  # one level per sample for all target frames
    assert 0.3 < tau[:, 3].mean() < 0.7 and tau[:, 3].std() > 0.2
    # A model that outputs zero pays E|eps - x|^2 = 2 for unit data.
    zero_loss, _ = teacher_forcing_loss(Spy(), context, target, gen(3))
    assert 1.5 < zero_loss.item() < 2.5


def test_teacher_forcing_context_augmentation_and_dropout():
    context, target = torch.randn(8, 2, 3, 4, 4, generator=gen(1)), torch.randn(8, 1, 3, 4, 4, generator=gen(2))
    spy = Spy()
    _, metrics = teacher_forcing_loss(spy, context, target, gen(3), context_noise_prob=1.0, context_noise_std=0.1)
    x, tau, _ = spy.calls[0]
    assert metrics["context_noised"] == 1.0 and torch.all(tau[:, :2] == 0)
    assert 0.05 < (x[:, :2] - context).std() < 0.15
    spy = Spy()
    _, metrics = teacher_forcing_loss(spy, context, target, gen(3), context_drop_prob=1.0)
    x, tau, _ = spy.calls[0]
    assert metrics["context_dropped"] == 1.0
    assert torch.all(x[:, :2] == 0) and torch.all(tau[:, :2] == NULL_CONTEXT_TAU)
    spy = Spy()
    _, metrics = teacher_forcing_loss(spy, context, target, gen(3), context_drop_prob=0.5)
    dropped = (spy.calls[0][1][:, 0] == NULL_CONTEXT_TAU)
    assert metrics["context_dropped"] == dropped.float().mean().item()
    assert torch.equal(spy.calls[0][0][~dropped, :2], context[~dropped])


def test_losses_are_deterministic_given_the_generator():
    frames = torch.randn(4, 5, 2, 3, 3, generator=gen(1))

    def model(x, tau):
        return x * tau[..., None, None, None]

    first, _ = diffusion_forcing_loss(model, frames, gen(7))
    second, _ = diffusion_forcing_loss(model, frames, gen(7))
    other, _ = diffusion_forcing_loss(model, frames, gen(8))
    assert first.item() == second.item() != other.item()
    tf1, _ = teacher_forcing_loss(model, frames[:, :3], frames[:, 3:], gen(7), 0.5, 0.1, 0.2)
    tf2, _ = teacher_forcing_loss(model, frames[:, :3], frames[:, 3:], gen(7), 0.5, 0.1, 0.2)
    assert tf1.item() == tf2.item()


def test_diffusion_forcing_draws_independent_uniform_levels_per_frame():
    frames = torch.randn(4096, 6, 1, 2, 2, generator=gen(1), dtype=torch.float64)
    spy = Spy(oracle(frames))
    loss, _ = diffusion_forcing_loss(spy, frames, gen(2))
    assert loss.item() < 1e-20  # loss on all frames is zero for the exact velocity
    tau = spy.calls[0][1]
    assert tau.shape == (4096, 6) and tau.min() >= 0 and tau.max() <= 1
    distinct = torch.stack([tau[:, i] != tau[:, j] for i in range(6) for j in range(i + 1, 6)])
    assert distinct.all()  # levels differ across the frames of a sample
    corr = torch.corrcoef(tau.T)
    off_diagonal = corr[~torch.eye(6, dtype=torch.bool)]
    assert off_diagonal.abs().max() < 0.06
    assert abs(tau.mean().item() - 0.5) < 0.01 and abs(tau.var().item() - 1 / 12) < 0.005
    histogram = torch.histc(tau.float(), bins=10, min=0, max=1) / tau.numel()
    assert (histogram - 0.1).abs().max() < 0.01


def test_euler_transports_noise_to_a_known_gaussian():
    """Data ~ N(mu, s^2): E[eps - x | x_tau = z] is linear in z, so the sampler must land on N(mu, s^2)."""
    mu, s = 2.0, 0.5

    def velocity(x, tau):
        t = tau.reshape(*tau.shape, 1, 1, 1).to(x.dtype)
        var = (1 - t) ** 2 * s**2 + t**2
        centred = x - (1 - t) * mu
        return t / var * centred - (mu + (1 - t) * s**2 / var * centred)

    context = torch.zeros(20000, 1, 1, 1, 1)
    spy = Spy(velocity)
    samples = euler_sample(spy, context, n_target=1, nfe=100, generator=gen(3))
    assert samples.shape == (20000, 1, 1, 1, 1) and len(spy.calls) == 100
    assert abs(samples.mean().item() - mu) < 0.02
    assert abs(samples.std().item() - s) < 0.02
    levels = [call[1][0].tolist() for call in spy.calls]
    assert levels[0] == [0.0, 1.0] and levels[-1][0] == 0.0 and abs(levels[-1][1] - 0.01) < 1e-6
    again = euler_sample(velocity, context[:8], 1, 10, gen(3))
    assert torch.equal(again, euler_sample(velocity, context[:8], 1, 10, gen(3)))


@pytest.mark.parametrize("n_context", [0, 2])
def test_euler_keeps_the_context_clean(n_context):
    context = torch.randn(2, n_context, 3, 2, 2, generator=gen(1))
    spy = Spy(lambda x, tau: torch.ones_like(x))
    out = euler_sample(spy, context, n_target=2, nfe=4, generator=gen(2), frame_rate=10.0)
    noise = torch.randn(2, 2, 3, 2, 2, generator=gen(2))
    torch.testing.assert_close(out, noise - 1.0)  # integrates dx/dtau = 1 from tau = 1 to 0
    for x, tau, cond in spy.calls:
        assert torch.equal(x[:, :n_context], context) and torch.all(tau[:, :n_context] == 0)
        assert cond == {"frame_rate": 10.0}
