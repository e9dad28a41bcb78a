"""params.yaml resolution: profiles, strict keys, types and impossible values, and params.yaml as the one source."""

import copy
import dataclasses
import re
import subprocess
import sys
import typing

import pytest
import yaml

from orbis2.config.params import PROFILES, load_config, load_params, section_types
from orbis2.config.sections import ASSETS_DIR
from orbis2.errors import ConfigError
from orbis2.registry import registry

from conftest import ROOT


def write_params(tmp_path, mutate):
    raw = copy.deepcopy(load_params(ROOT / "params.yaml"))
    mutate(raw)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_resolves(profile):
    cfg = load_config(ROOT / "params.yaml", profile)
    assert cfg.profile == profile
    assert cfg.data.fps % cfg.data.detail_hz == 0 and cfg.data.fps % cfg.data.abstract_hz == 0


@pytest.mark.parametrize("profile", PROFILES)
def test_a_predictor_started_from_another_has_its_architecture(profile):
    """``init_from`` loads weights strictly (only a steered fine-tune adds its steering modules), so the
    preset and ``model`` overrides must repeat the source's."""
    cfg = load_config(ROOT / "params.yaml", profile)
    steering_only = {"steering_shift"}
    for name in registry().predictors:
        section = cfg.section(name)
        if getattr(section, "init_from", None) is None:
            continue
        source = cfg.section(section.init_from)
        assert section.preset == source.preset, name
        assert ({k: v for k, v in section.model.items() if k not in steering_only}
                == {k: v for k, v in source.model.items() if k not in steering_only}), name


def test_profile_key_selects_values(tmp_path):
    path = write_params(tmp_path, lambda raw: raw.update(profile="smoke"))
    assert load_config(path).data.width == 128
    assert load_config(path, "paper").data.width == 512  # an explicit profile wins


@pytest.mark.parametrize("mutate, key", [
    (lambda r: r["town"]["all"].update(sede=1), "town.smoke: unknown key(s) ['sede']"),
    (lambda r: r["data"]["all"].update(fps="ten"), "data.smoke.fps must be int, got 'ten' (str)"),
    (lambda r: r["data"]["all"].update(fps=25), "data.smoke.fps = 25 must be an integer multiple of detail_hz"),
    (lambda r: r["data"]["all"].update(fps=15), "data.smoke.fps = 15 must be an integer multiple of detail_hz"),
    (lambda r: r["shards"]["smoke"]["clip_seconds"].update(train=1.0), "clip_seconds.train = 1.0 is shorter"),
    (lambda r: r["town"]["smoke"]["episodes"].pop("probe"), "town.smoke.episodes must name exactly the splits"),
    (lambda r: r["town"]["all"].update(workers=True), "town.smoke.workers must be int, got True (bool)"),
    (lambda r: r["action"]["all"].update(speed_scale="fast"), "action.smoke.speed_scale must be float, got 'fast'"),
    (lambda r: r["evaluation"]["all"]["probe"].update(kitti=3), "evaluation.smoke.probe.kitti must be str, got 3"),
    (lambda r: r["_predictor"]["all"]["train"].update(betas=[0.9]),
     "abstract_df.smoke.train.betas must be tuple[float, float], got [0.9]"),
    (lambda r: r["_tokenizer"].pop("gpu"), "_tokenizer: no ['gpu']; every section names 'all' and each profile"),
    (lambda r: r.update(_unused={"all": {}}), "_unused: no ['smoke', 'default', 'gpu', 'paper']"),
    (lambda r: r.update(train_launcher=3), "train_launcher = 3 must be a command"),
    (lambda r: r.update(profile="huge"), "profile = 'huge' must be one of"),
    (lambda r: r["evaluation"]["smoke"].update(steering_guidance=-1.0),
     "evaluation.smoke.steering_guidance = -1.0 must be >= 0"),
    (lambda r: r.update(extra={}), "unknown top-level key(s) ['extra']"),
    (lambda r: r["data"].update(large={}), "data: unknown key(s) ['large']"),
    (lambda r: r["detail"]["smoke"].update(preset="huge"), "detail.smoke.preset = 'huge' must be one of"),
    (lambda r: r["tokenizer_detail"]["smoke"].update(preset="huge"), "tokenizer_detail.smoke.preset = 'huge' must be"),
    (lambda r: r["detail"]["smoke"].update(model={"hiden_size": 64}),
     "detail.smoke.model: ST-DiT: unknown key 'hiden_size' (known: abstract_positions, causal_mask, cond_dim,"),
    (lambda r: r["detail"]["smoke"].update(model={"depth": 2.5}),
     "detail.smoke.model: ST-DiT: depth must be int, got 2.5"),
    (lambda r: r["detail"]["smoke"].update(model={"num_heads": 3}),
     "detail.smoke.model: ST-DiT: hidden_size = 64 is not divisible by num_heads = 3"),
    (lambda r: r["_tokenizer"]["smoke"].update(model={"patch_size": 4}),
     "tokenizer_detail.smoke.model: tokenizer: decoder_mult: the decoder upsamples x8 but the patch size is 4"),
    (lambda r: r["tokenizer_detail"]["smoke"].update(model={"patch_size": 4, "decoder_mult": [1, 2, 4],
                                                            "abstract_decoder_mult": [1, 1, 2]}),
     "smoke: the tokenizers must share one latent grid"),
])
def test_bad_values_name_the_key(tmp_path, mutate, key):
    def apply(raw):
        raw["profile"] = "smoke"
        mutate(raw)

    with pytest.raises(ConfigError) as err:
        load_config(write_params(tmp_path, apply))
    assert key in str(err.value)


def test_the_tokenizers_latent_grid_is_a_size_override_every_tokenizer_section_shares(tmp_path):
    grid = {"patch_size": 4, "decoder_mult": [1, 2, 4], "abstract_decoder_mult": [1, 1, 2]}
    cfg = load_config(write_params(tmp_path, lambda r: r["_tokenizer"]["smoke"].update(model=grid)), "smoke")
    for name in ("tokenizer_detail", "tokenizer_abstract", "tokenizer_abstract_full"):
        sizes = cfg.section(name).sizes()
        assert (sizes.patch_size, sizes.decoder_mult, sizes.abstract_decoder_mult) == (4, (1, 2, 4), (1, 1, 2)), name


def test_native_rate_of_twenty_is_accepted(tmp_path):
    path = write_params(tmp_path, lambda r: r["data"]["all"].update(fps=20))
    cfg = load_config(path, "smoke")
    assert (cfg.data.detail_stride, cfg.data.abstract_stride) == (2, 10)


def test_a_key_given_twice_is_an_error(tmp_path):
    text = (ROOT / "params.yaml").read_text()
    twice = "    dir: data/assets\n    download: false\n    download: true\n"
    doubled = text.replace("    dir: data/assets\n", twice, 1)
    assert doubled != text
    path = tmp_path / "params.yaml"
    path.write_text(doubled)
    with pytest.raises(ConfigError) as err:
        load_config(path, "smoke")
    assert str(path) in str(err.value) and "'download' is given twice" in str(err.value)


def test_assets_dir_must_be_the_dags_output(tmp_path):
    from test_dag import dvc_stages

    assert dvc_stages()["assets"]["outs"] == {ASSETS_DIR}
    path = write_params(tmp_path, lambda r: r["assets"]["all"].update(dir="/big/disk/assets"))
    with pytest.raises(ConfigError, match="dir = '/big/disk/assets' differs .* make data/assets a symlink"):
        load_config(path, "smoke")
    assert load_config(write_params(tmp_path, lambda r: r["assets"]["all"].update(dir="data/assets/")), "smoke")


# --------------------------------------------------------------------------- one source of every value


def typed_fields(cls, prefix=""):
    """``(dotted name, field)`` of every field of section type ``cls``, nested sections (``train``, ...) included."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            yield from typed_fields(hints[f.name], f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def test_no_section_field_has_a_default():
    """params.yaml is the one source: a default in the code would silently take over when a key is missing."""
    with_default = [f"{name}.{key}" for name, cls in section_types().items() for key, f in typed_fields(cls)
                    if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING]
    assert with_default == []


def test_a_key_missing_from_params_yaml_is_an_error_naming_section_key_and_file(tmp_path):
    path = write_params(tmp_path, lambda r: r["action"]["all"].pop("yaw_rate_scale"))
    with pytest.raises(ConfigError) as err:
        load_config(path, "smoke")
    message = str(err.value)
    assert str(path) in message and "section 'action'" in message and "['yaw_rate_scale']" in message
    assert "add it under action.all (or in the section it extends, _fine_tune -> _teacher_forcing" in message
    nested = write_params(tmp_path, lambda r: r["_predictor"]["all"]["train"].pop("min_lr_ratio"))
    with pytest.raises(ConfigError, match=r"section 'abstract_df' has no value for \['train.min_lr_ratio'\]"):
        load_config(nested, "smoke")


def test_reading_the_dag_needs_no_torch():
    """Every Snakemake invocation reads params.yaml (each stage's preset and size overrides are checked) and
    the modules the Snakefile and rules import at the top: none of that imports torch (1.2-1.8 s a process)."""
    sources = [ROOT / "Snakefile", *sorted((ROOT / "rules").glob("*.smk"))]
    modules = sorted({m for f in sources for m in re.findall(r"^from (orbis2[\w.]*) import", f.read_text(), re.M)})
    assert "orbis2.config.params" in modules
    code = (f"import sys, {', '.join(modules)}\n"
            "from orbis2.config.params import PROFILES, load_config\n"
            "for profile in PROFILES: load_config('params.yaml', profile)\n"
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", f"reading the DAG imported torch: {out[:300]}"
