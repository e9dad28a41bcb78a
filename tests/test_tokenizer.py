"""Tokenizer blocks, presets and tokenizer losses: fast checks on CPU (and the meta device)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from orbis2.data.images import to_uint8
from orbis2.losses import (
    adaptive_gan_weight,
    entropy_weight,
    generator_gan_loss,
    hinge_d_loss,
    l1_reconstruction,
    psnr,
    ssim,
    teacher_alignment_loss,
)
from orbis2.models.discriminator import PatchGANDiscriminator, build_discriminator
from orbis2.models.sizes import TOKENIZER_PRESETS, tokenizer_config
from orbis2.models.tokenizer import (
    VectorQuantizer,
    ViTEncoder,
    build_abstract_tokenizer,
    build_detail_tokenizer,
    codebook_usage,
    load_mae_encoder,
)


def n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def structured_images(n: int, height: int, width: int) -> torch.Tensor:
    """Sines, stripes and checkers in [-1, 1]: content a decoder must actually learn."""
    ys = torch.linspace(-1, 1, height).view(height, 1).expand(height, width)
    xs = torch.linspace(-1, 1, width).view(1, width).expand(height, width)
    images = []
    for i in range(n):
        red = torch.sin(3 * (i + 1) * xs)
        green = 0.8 * torch.sign(torch.sin(4 * math.pi * ys + i))
        blue = ((xs * (i + 2)).floor() % 2) * 1.6 - 0.8
        images.append(torch.stack([red, green, blue]))
    return torch.stack(images)


def unit_latents(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    return F.normalize(torch.randn(shape, generator=torch.Generator().manual_seed(seed)), dim=1)


# --------------------------------------------------------------------------- quantiser


def test_vq_picks_nearest_code_and_passes_gradient_straight_through():
    vq = VectorQuantizer(codebook_size=32, latent_dim=16, bypass_prob=0.0).train()
    z = unit_latents((2, 16, 3, 5)).requires_grad_()
    out = vq(z)

    codes = vq.normalized_codebook().detach()
    expected = (z.detach().permute(0, 2, 3, 1) @ codes.t()).argmax(-1)
    assert torch.equal(out.indices, expected)
    torch.testing.assert_close(out.quantized.detach(), vq.lookup(out.indices).detach())

    upstream = torch.randn_like(z)
    (out.quantized * upstream).sum().backward()
    assert torch.equal(z.grad, upstream)


def test_vq_losses_and_entropy_term():
    vq = VectorQuantizer(codebook_size=64, latent_dim=16, beta=0.25).train()
    z = unit_latents((2, 16, 4, 4))
    out = vq(z)
    distance = F.mse_loss(vq.lookup(out.indices), z)
    torch.testing.assert_close(out.codebook_loss, distance)
    torch.testing.assert_close(out.commitment_loss, 0.25 * distance)
    assert out.entropy_loss.ndim == 0 and torch.isfinite(out.entropy_loss)
    assert 1.0 <= out.perplexity <= 32 and 0 < out.used_fraction <= 32 / 64
    assert vq.eval()(z).entropy_loss == 0


def test_codebook_usage_statistics():
    uniform = codebook_usage(torch.arange(16).repeat(5), codebook_size=16)
    assert uniform["perplexity"] == pytest.approx(16.0)
    assert uniform["dead_codes"] == 0 and uniform["used_fraction"] == 1.0

    three_of_eight = codebook_usage(torch.tensor([[0, 1], [2, 0], [1, 2]]), codebook_size=8)
    assert three_of_eight["perplexity"] == pytest.approx(3.0)
    assert three_of_eight["dead_codes"] == 5
    assert three_of_eight["used_fraction"] == pytest.approx(3 / 8)

    skewed = codebook_usage(torch.tensor([4, 4, 4, 7]), codebook_size=10)
    p = torch.tensor([0.75, 0.25])
    assert skewed["perplexity"] == pytest.approx(float(torch.exp(-(p * p.log()).sum())))
    assert skewed["dead_codes"] == 8


def test_bypass_probability_is_respected_per_sample():
    torch.manual_seed(0)
    n = 4000
    vq = VectorQuantizer(codebook_size=8, latent_dim=4, bypass_prob=0.3).train()
    z = unit_latents((n, 4, 1, 1))
    out = vq(z)
    # Binomial(4000, 0.3) has a standard deviation of 0.0072 in the fraction: 5 sigma.
    assert abs(out.bypassed.float().mean().item() - 0.3) < 0.036
    torch.testing.assert_close(out.quantized[out.bypassed], z[out.bypassed])
    kept = ~out.bypassed
    torch.testing.assert_close(out.quantized[kept], vq.lookup(out.indices)[kept])

    assert not vq.eval()(z).bypassed.any()
    assert VectorQuantizer(8, 4, bypass_prob=1.0).train()(z).bypassed.all()
    assert not VectorQuantizer(8, 4, bypass_prob=0.0).train()(z).bypassed.any()


# --------------------------------------------------------------------------- shapes and sizes


@pytest.mark.parametrize("preset", ["smoke", "default", "paper"])
def test_shapes_at_every_preset(preset):
    cfg = TOKENIZER_PRESETS[preset]
    height, width = cfg.image_size
    grid = (height // cfg.patch_size, width // cfg.patch_size)
    device = torch.device("meta") if preset == "paper" else torch.device("cpu")
    with device:
        detail = build_detail_tokenizer(preset).eval()
        abstract = build_abstract_tokenizer(preset, teacher_dim=48).eval()
        rae = build_abstract_tokenizer(preset, teacher_dim=48, compress=False).eval()
        disc = build_discriminator(preset)
        images = torch.zeros(2, 3, height, width)
    assert grid == {"smoke": (9, 16), "default": (10, 16), "paper": (18, 32)}[preset]

    with torch.no_grad():
        assert detail.encoder(images).shape == (2, cfg.embed_dim, *grid)
        z = detail.encode(images)
        assert z.shape == (2, 16, *grid)
        recon, vq = detail(images)
        assert recon.shape == images.shape and detail.decode(z).shape == images.shape
        assert vq.indices.shape == (2, *grid)

        z_abs, pred, recon_abs = abstract(images)
        assert z_abs.shape == (2, 16, *grid) and pred.shape == (2, 48, *grid)
        assert recon_abs.shape == images.shape

        z_rae, pred_rae, recon_rae = rae(images)
        assert z_rae.shape == pred_rae.shape == (2, 48, *grid)
        assert recon_rae.shape == images.shape
        assert disc(images).shape[:2] == (2, 1)
    if preset != "paper":
        norms = z.norm(dim=1)
        torch.testing.assert_close(norms, torch.ones_like(norms))


def test_paper_preset_parameter_counts():
    """Paper Sec. 4.2: the encoder has 86M parameters and the decoder 91M."""
    with torch.device("meta"):
        detail = build_detail_tokenizer("paper")
        abstract = build_abstract_tokenizer("paper", teacher_dim=768)
    assert n_params(detail.encoder) == pytest.approx(86e6, rel=0.05)
    assert n_params(detail.decoder) == pytest.approx(91e6, rel=0.05)
    assert n_params(abstract.encoder) == n_params(detail.encoder)
    assert n_params(abstract.decoder) < 0.1 * n_params(detail.decoder)
    assert detail.quantizer.codebook.shape == (16384, 16)


def test_overrides_are_checked():
    cfg = tokenizer_config("smoke", codebook_size=64, decoder_mult=[1, 2, 2, 4])
    assert cfg.codebook_size == 64 and cfg.decoder_mult == (1, 2, 2, 4)  # a list from YAML becomes a tuple
    assert build_detail_tokenizer(cfg).quantizer.codebook.shape == (64, 16)
    with pytest.raises(ValueError, match="tokenizer: unknown key 'codebook_sise' \\(known: "):
        tokenizer_config("smoke", codebook_sise=64)
    with pytest.raises(ValueError, match="tokenizer: image_size must be tuple\\[int, int\\], got \\(72, 128, 3\\)"):
        tokenizer_config("smoke", image_size=(72, 128, 3))
    with pytest.raises(ValueError, match="tokenizer: disc_norm must be str, got 1"):
        tokenizer_config("smoke", disc_norm=1)
    with pytest.raises(ValueError, match="unknown preset 'huge'"):
        build_detail_tokenizer("huge")
    with pytest.raises(ValueError, match="decoder_mult: the decoder upsamples x2 but the patch size is 8"):
        tokenizer_config("smoke", decoder_mult=(1, 2))
    with pytest.raises(ValueError, match=r"image_size = \(72, 120\) is not divisible by patch_size = 16"):
        tokenizer_config("smoke", image_size=(72, 120), patch_size=16)


def test_load_mae_encoder_maps_official_keys(tmp_path):
    """A checkpoint in MAE's layout (CLS token, square 4x4 pos_embed, decoder keys) loads."""
    torch.manual_seed(0)
    source = ViTEncoder((64, 64), patch_size=16, embed_dim=32, depth=2, num_heads=2)
    state = {k: torch.randn_like(v) for k, v in source.state_dict().items() if k != "pos_embed"}
    state["pos_embed"] = torch.randn(1, 1 + 16, 32)
    state["cls_token"] = torch.randn(1, 1, 32)
    state["mask_token"] = torch.randn(1, 1, 32)
    state["decoder_embed.weight"] = torch.randn(16, 32)
    torch.save({"model": state}, tmp_path / "mae.pth")

    target = ViTEncoder((48, 96), patch_size=16, embed_dim=32, depth=2, num_heads=2)
    load_mae_encoder(target, tmp_path / "mae.pth")
    loaded = target.state_dict()
    assert torch.equal(loaded["blocks.1.attn.qkv.weight"], state["blocks.1.attn.qkv.weight"])
    assert torch.equal(loaded["patch_embed.proj.weight"], state["patch_embed.proj.weight"])
    assert loaded["pos_embed"].shape == (1, 3 * 6, 32)
    assert target(torch.zeros(1, 3, 48, 96)).shape == (1, 32, 3, 6)

    del state["norm.weight"]
    torch.save(state, tmp_path / "broken.pth")
    with pytest.raises(RuntimeError):
        load_mae_encoder(target, tmp_path / "broken.pth")


# --------------------------------------------------------------------------- training signals


def test_smoke_detail_tokenizer_overfits_a_fixed_batch():
    torch.manual_seed(0)
    tokenizer = build_detail_tokenizer("smoke")
    height, width = TOKENIZER_PRESETS["smoke"].image_size
    images = structured_images(2, height, width)
    optimiser = torch.optim.Adam(tokenizer.parameters(), lr=2e-3, betas=(0.5, 0.9))

    def quantised_l1() -> float:
        tokenizer.eval()
        with torch.no_grad():
            error = l1_reconstruction(tokenizer(images)[0], images).item()
        tokenizer.train()
        return error

    initial = quantised_l1()
    for step in range(100):
        recon, vq = tokenizer(images)
        loss = l1_reconstruction(recon, images) + vq.vq_loss + entropy_weight(step) * vq.entropy_loss
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert quantised_l1() < 0.5 * initial


def test_teacher_alignment_falls_for_abstract_tokenizer():
    torch.manual_seed(0)
    tokenizer = build_abstract_tokenizer("smoke", teacher_dim=32)
    height, width = TOKENIZER_PRESETS["smoke"].image_size
    images = structured_images(2, height, width)
    # A fixed random low-rank "teacher" on a grid unlike ours (resized inside the loss).
    gen = torch.Generator().manual_seed(1)
    mixing = torch.randn(32, 4, generator=gen) / 2
    teacher = torch.einsum("oc,bchw->bohw", mixing, torch.randn(2, 4, 7, 12, generator=gen))
    optimiser = torch.optim.Adam(tokenizer.parameters(), lr=5e-3)

    losses = []
    for _ in range(40):
        z, pred, recon = tokenizer(images)
        align = teacher_alignment_loss(pred, teacher)
        loss = align + 0.1 * F.mse_loss(recon, images)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(align.item())
    assert losses[-1] < 0.7 * losses[0]


def test_adaptive_gan_weight_is_finite_and_positive():
    torch.manual_seed(0)
    tokenizer = build_detail_tokenizer("smoke")
    disc = build_discriminator("smoke")
    height, width = TOKENIZER_PRESETS["smoke"].image_size
    images = structured_images(2, height, width)
    recon, _ = tokenizer(images)
    weight = adaptive_gan_weight(
        l1_reconstruction(recon, images), generator_gan_loss(disc(recon)), tokenizer.last_layer
    )
    assert weight.ndim == 0 and torch.isfinite(weight) and weight > 0
    assert not weight.requires_grad


def test_patchgan_norm_choices():
    images = torch.zeros(2, 3, 64, 64)
    for norm in ("group", "batch"):
        assert PatchGANDiscriminator(norm=norm)(images).shape == (2, 1, 6, 6)
    with pytest.raises(ValueError):
        PatchGANDiscriminator(norm="layer")


# --------------------------------------------------------------------------- loss invariants


def test_gan_losses_at_known_logits():
    ones = torch.ones(4, 1, 3, 3)
    assert hinge_d_loss(ones, -ones) == 0
    assert hinge_d_loss(0 * ones, 0 * ones) == 1
    assert hinge_d_loss(-ones, ones) == 2
    assert hinge_d_loss(3 * ones, -3 * ones) == 0
    assert generator_gan_loss(2 * ones) == -2


def test_teacher_alignment_loss_values():
    pred = torch.zeros(2, 4, 3, 5)
    target = torch.ones(2, 4, 3, 5)
    assert teacher_alignment_loss(pred, target) == pytest.approx(4.0)
    assert teacher_alignment_loss(target, 2 * target, kind="cosine") == pytest.approx(0.0, abs=1e-6)
    assert teacher_alignment_loss(target, -target, kind="cosine") == pytest.approx(2.0)
    assert teacher_alignment_loss(target, torch.ones(2, 4, 7, 9)) == pytest.approx(0.0)
    with pytest.raises(ValueError):
        teacher_alignment_loss(pred, target, kind="l1")


def test_entropy_weight_schedule():
    assert entropy_weight(0) == pytest.approx(0.01)
    assert entropy_weight(5000) == pytest.approx(0.0055)
    assert entropy_weight(10000) == pytest.approx(0.001)
    assert entropy_weight(50000) == pytest.approx(0.001)


def test_image_metrics():
    torch.manual_seed(0)
    x = structured_images(2, 32, 48)
    assert torch.isinf(psnr(x, x))
    assert psnr(torch.zeros(1, 3, 8, 8), torch.full((1, 3, 8, 8), 0.2)) == pytest.approx(20.0, abs=1e-4)
    assert psnr(x, x, reduction="none").shape == (2,)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-5)
    noisy = (x + 0.3 * torch.randn_like(x)).clamp(-1, 1)
    assert ssim(x, noisy) < 0.9
    assert ssim(x, noisy, reduction="none").shape == (2,)
    assert l1_reconstruction(x, x) == 0


def test_to_uint8_maps_the_decoder_range_to_bytes_channels_last():
    images = torch.tensor([-1.0, 0.0, 1.0, -3.0, 3.0, 0.5]).view(1, 3, 1, 2)
    pixels = to_uint8(images)
    assert pixels.dtype.name == "uint8" and pixels.shape == (1, 1, 2, 3)
    # channel c of pixel (0, w) is images[0, c, 0, w]; out-of-range values saturate
    assert pixels[0, 0].tolist() == [[0, 255, 255], [128, 0, 191]]
