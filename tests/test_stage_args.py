"""Stage scripts get their paths from the DAG as options, and fall back on registry.yaml's layout by hand."""

import argparse
from pathlib import Path

import pytest

from orbis2.errors import OrbisError
from orbis2.registry import layout_path
from orbis2.stage import (
    add_latent_arguments,
    add_predictor_argument,
    latent_paths,
    named_path,
    predictor_files,
)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_latent_arguments(p)
    add_predictor_argument(p)
    return p


def test_paths_given_as_options_are_used():
    args = parser().parse_args(["--latents", "/x/cache", "--detail-tokenizer", "/x/det", "--abstract-tokenizer",
                                "/x/abs", "--predictor", "detail=/x/p/detail", "--predictor", "action=/y/action"])
    paths = latent_paths(args, "full")
    assert paths.root == Path("/x/cache")
    assert paths.tokenizers == {"detail": Path("/x/det/tokenizer.pt"), "abstract": Path("/x/abs/tokenizer.pt")}
    assert predictor_files(args, ["action", "detail"]) == {"action": Path("/y/action/predictor.pt"),
                                                          "detail": Path("/x/p/detail/predictor.pt")}


def test_without_options_the_registry_layout_is_used():
    args = parser().parse_args([])
    paths = latent_paths(args, "full")
    assert paths.root == layout_path("latents", "latents_full")
    assert paths.tokenizers["abstract"] == layout_path("tokenizer", "abstract_full") / "tokenizer.pt"
    detail = layout_path("predictor", "detail") / "predictor.pt"
    assert predictor_files(args, ["detail", "detail"]) == {"detail": detail}


def test_a_predictor_the_stage_does_not_read_is_an_error():
    args = parser().parse_args(["--predictor", "detial=/x"])
    with pytest.raises(OrbisError, match="--predictor detial: not read by this stage; it reads detail"):
        predictor_files(args, ["detail"])
    with pytest.raises(argparse.ArgumentTypeError, match="NAME=PATH"):
        named_path("data/predictors/detail")
