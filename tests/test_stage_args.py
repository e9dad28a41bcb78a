"""Stage scripts get their paths from the DAG as options, and fall back on registry.yaml's layout by hand."""

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from orbis2.errors import OrbisError
from orbis2.interfaces import INTERFACES
from orbis2.registry import layout_path
from orbis2.stage import add_path_options, latent_paths, named_path, predictor_files


def parser() -> argparse.ArgumentParser:
    """The latent cache, tokenizer and predictor options, as the steering stage declares them."""
    p = argparse.ArgumentParser()
    add_path_options(p, [o for o in INTERFACES["eval_steering"].paths
                         if o.key in ("latents", "detail_tokenizer", "abstract_tokenizer", "predictor")])
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


def test_a_stage_process_freezes_its_imports_now_and_once_more_at_exit():
    """freeze_imports: the heap imported so far leaves the collector's sight, and one exit handler freezes the rest."""
    code = ("import atexit, gc\n"
            "from orbis2.stage import freeze_imports\n"
            "handlers = atexit._ncallbacks()\n"
            "freeze_imports(); freeze_imports()\n"
            "assert gc.get_freeze_count() > 10_000, gc.get_freeze_count()\n"
            "assert atexit._ncallbacks() == handlers + 1\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
