"""registry.yaml: the entries the DAG is built from, cross-checked, with errors that name the entry."""

import pickle

import pytest
import yaml

from orbis2.registry import RegistryError, layout_path, parse_registry, registry

from conftest import ROOT


def raw() -> dict:
    return yaml.safe_load((ROOT / "registry.yaml").read_text())


def test_the_project_registry_describes_the_paper_dag():
    reg = registry()
    assert list(reg.table("main")) == ["hierarchical"]
    assert list(reg.table("all")) == ["flat_detail", "flat_abstract", "hierarchical"]  # the baselines first
    assert reg.main_table["hierarchical"] == "abstract_tf"  # the hierarchy is probed at its top predictor
    assert reg.table_predictors("main") == ["abstract_tf", "detail"]
    assert reg.table_predictors("all") == ["abstract_tf", "detail", "flat_detail", "flat_abstract"]
    assert list(reg.timed_systems("main")) == ["hierarchical"]  # the distilled hierarchy is an addition: all only
    assert list(reg.timed_systems("all")) == ["flat_detail", "flat_abstract", "hierarchical", "hierarchical_distilled"]
    assert reg.systems["hierarchical"].stages == ["abstract_tf", "detail"]
    assert "action" not in reg.probe_targets and "teacher" in reg.probe_targets
    assert reg.predictors["action"].steering and reg.predictors["abstract_df"].causal
    assert reg.steered == "action"
    full_abstract = layout_path("tokenizer", "abstract_full") / "tokenizer.pt"
    assert reg.latent_sets["full"].tokenizer_file("abstract") == full_abstract
    assert reg.target_latents("flat_abstract_full") == "full"


@pytest.mark.parametrize("edit, message", [
    (lambda r: r["predictors"]["detail"].update(rate="medium"), "predictors.detail.rate = 'medium'"),
    (lambda r: r["predictors"]["detail"].update(colour="red"), "predictors.detail: .*colour"),
    (lambda r: r["systems"]["hierarchical"].update(top="abstract_tff"),
     "systems.hierarchical: predictor 'abstract_tff'"),
    (lambda r: r["latent_sets"]["full"]["tokenizers"].update(abstract="nope"), "latent_sets.full.tokenizers.abstract"),
    (lambda r: r["main_table"].update(hierarchical="action"), "main_table.hierarchical"),
    (lambda r: r["baselines"].update(flat_video="flat_detail"), "baselines.flat_video"),
    (lambda r: r["baselines"].update(hierarchical="abstract_tf"), "baselines.hierarchical: already a main_table row"),
    (lambda r: r["predictors"]["detail"].update(steering=True), "exactly one .*found detail, action"),
    (lambda r: r["predictors"]["action"].update(steering=False), "exactly one .*found none"),
])
def test_a_bad_entry_is_named(edit, message):
    data = raw()
    edit(data)
    with pytest.raises(RegistryError, match=message):
        parse_registry(data)


def test_layout_paths():
    assert str(layout_path("predictor", "detail")) == "data/predictors/detail"
    assert str(layout_path("shards")) == "data/shards"
    with pytest.raises(RegistryError, match="layout has no 'nowhere'"):
        layout_path("nowhere")


def test_registry_names_pickle_like_literals():
    """Checkpoint meta holds registry strings; interned, they pickle byte-identically to the literals."""
    spec = registry().predictors["detail"]
    from_registry = [spec.level, spec.rate, spec.objective, spec.condition, "detail", "abstract"]
    assert pickle.dumps(from_registry) == pickle.dumps(["detail", "fast", "teacher_forcing", "abstract", "detail",
                                                        "abstract"])
