"""Publish a finished run's results into a folder that can be committed: docs/results/<profile>/.

    python tools/publish_results.py                      # this project's last run, profile from reports
    python tools/publish_results.py --root ../other-run  # a run made in another clone
    python tools/publish_results.py --mark-stale default --why "params changed: detail steps 600 -> 800"

Run it on the machine that made the run, right after it: the folder records this machine. It copies
`reports/summary.md` and the main tables, writes the stage times from the rules' benchmark files
(`logs/benchmarks/<rule>.tsv`), and `run.json` with the profile, the commit, the date, the machine and
the profile's resolved params. The README links these files instead of copying numbers, and a test
fails when a published folder's params differ from today's params.yaml unless it is marked stale.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pandas as pd
import torch
import yaml

from orbis2.config.params import PROFILES, as_dict, load_params, parse_config
from orbis2.io import atomic_file

TABLES = ("main_table.csv", "steering.csv", "speed.csv", "conditioning.csv")
PICTURES = ("town_contact_sheet.png", "headline.png")
RESULTS = Path("docs/results")


def profile_params(raw: dict, profile: str) -> dict:
    """The typed configuration params.yaml resolves to for ``profile``: every value the stages read, however
    the file spells it (shared bases `_...` folded in), as JSON-ready values."""
    return json.loads(json.dumps(as_dict(parse_config({**raw, "profile": profile}, profile)), default=str))


def same_params(published: Any, today: Any) -> bool:
    """Whether a published run's params are today's. A setting added after the run, at any depth, counts as the
    same when it is off today, null or an empty mapping (no overrides): the behaviour the run had without it."""
    if not (isinstance(published, dict) and isinstance(today, dict)):
        return published == today
    added = {key for key in today.keys() - published.keys() if today[key] is None or today[key] == {}}
    return published.keys() == today.keys() - added and all(same_params(published[k], today[k]) for k in published)


def params_digest(params: dict) -> str:
    return hashlib.sha256(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_profile(summary: Path) -> str:
    """The profile the report stage wrote into the summary's set-up list (not params.yaml's `profile`,
    which a run may have overridden with `--config profile=...`)."""
    found = re.search(r"^- profile: (\w+)$", summary.read_text(), re.MULTILINE)
    if not found or found.group(1) not in PROFILES:
        raise SystemExit(f"{summary}: no '- profile: ...' line in its Setup section; re-run the report stage")
    return found.group(1)


def stage_times(folder: Path) -> pd.DataFrame:
    """One row per rule: the latest wall seconds and peak resident memory (MB), in finishing order."""
    files = sorted(folder.glob("*.tsv"), key=lambda path: path.stat().st_mtime)
    if not files:
        raise SystemExit(f"{folder}: no benchmark files; run the pipeline with Snakemake first")
    rows = [pd.read_csv(path, sep="\t").iloc[-1].rename(path.stem) for path in files]
    table = pd.DataFrame(rows)[["s", "max_rss"]].rename(columns={"s": "wall_s", "max_rss": "peak_rss_mb"})
    return table.rename_axis("stage").round(1)


def git_state(root: Path) -> dict:
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True).stdout

    changed = [line[3:] for line in git("status", "--porcelain", "--untracked-files=all").splitlines()]
    return {"commit": git("rev-parse", "HEAD").strip() or None,
            "uncommitted": sorted(path for path in changed if not written_by_the_run(root, path, git))}


def written_by_the_run(root: Path, path: str, git) -> bool:
    """What a run writes itself, not a change to the code that made it: DVC's record (dvc.lock, the .gitignore
    files of its outputs) and params.yaml's `profile` when the run took the one it was given
    (``--config profile=...``, docs/tracking.md)."""
    if path == "dvc.lock" or path.endswith("/.gitignore") and not git("ls-files", path).strip():
        return True
    if path != "params.yaml":
        return False
    committed = yaml.safe_load(git("show", "HEAD:params.yaml"))
    current = load_params(root / "params.yaml")
    return {**committed, "profile": None} == {**current, "profile": None}


def machine() -> dict:
    cpu = platform.processor()
    flags = ""
    if Path("/proc/cpuinfo").is_file():
        info = Path("/proc/cpuinfo").read_text()
        cpu = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")),
                   cpu)
        flags = next((line for line in info.splitlines() if line.startswith("flags")), "")
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30 if hasattr(os, "sysconf") else None
    return {"cpu": cpu, "cores": os.cpu_count(), "avx512": " avx512f" in flags,
            "memory_gib": round(memory, 1) if memory else None,
            "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
            "os": platform.platform(), "python": platform.python_version(), "torch": torch.__version__}


def index_page(record: dict, times: pd.DataFrame, tables: list[str], pictures: list[str]) -> str:
    """The folder's README: what run this is, then links to everything in it."""
    m = record["machine"]
    hardware = m["gpu"] or f"{m['cores']} CPU cores ({m['cpu']}{', AVX-512' if m['avx512'] else ''})"
    lines = [f"# Results: `{record['profile']}` profile", ""]
    if record.get("stale"):
        lines += [f"> **Stale**: {record['stale']}", ""]
    commit = record["commit"] or "not a git checkout"
    lines += [
        f"Published by `tools/publish_results.py` from a run finished {record['finished']} (UTC) at commit "
        f"`{commit}`{' with uncommitted changes' if record['uncommitted'] else ''}, on {hardware}, "
        f"{m['memory_gib']} GiB, torch {m['torch']}.",
        "",
        "- [summary.md](summary.md): the run's own summary (every table, with sample counts and intervals)",
        *[f"- [{name}]({name})" for name in tables],
        f"- [stage_times.csv](stage_times.csv): wall time and peak memory per stage, "
        f"{times['wall_s'].sum() / 60:.1f} min in all over {len(times)} stages",
        f"- [run.json](run.json): profile, commit, machine and the resolved params (digest "
        f"`{record['params_sha256']}`)",
        *[f"- [{name}]({name})" for name in pictures],
        "",
    ]
    return "\n".join(lines)


def publish(root: Path, out_root: Path) -> Path:
    reports = root / "reports"
    summary = reports / "summary.md"
    if not summary.is_file():
        raise SystemExit(f"{summary}: not found; run the main job first (snakemake --cores 2)")
    profile = run_profile(summary)
    params = profile_params(load_params(root / "params.yaml"), profile)
    times = stage_times(root / "logs/benchmarks")
    finished = dt.datetime.fromtimestamp(summary.stat().st_mtime, dt.timezone.utc)
    record = {"profile": profile, **git_state(root), "finished": finished.strftime("%Y-%m-%d %H:%M"),
              "published": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M"), "machine": machine(),
              "params_sha256": params_digest(params), "stale": None, "params": params}

    out = out_root / profile
    staging = out.with_name(f".{profile}.publishing")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    shutil.copy2(summary, staging / "summary.md")
    tables = [name for name in TABLES if (reports / name).is_file()]
    pictures = [name for name in PICTURES if (reports / name).is_file()]
    for name in tables + pictures:
        shutil.copy2(reports / name, staging / name)
    times.to_csv(staging / "stage_times.csv")
    (staging / "run.json").write_text(json.dumps(record, indent=1) + "\n")
    (staging / "README.md").write_text(index_page(record, times, tables, pictures))
    shutil.rmtree(out, ignore_errors=True)  # the folder is replaced whole: nothing half-written is left
    staging.rename(out)
    return out


def mark_stale(out_root: Path, profile: str, why: str) -> Path:
    """Keep a published folder whose params no longer match params.yaml, saying why."""
    path = out_root / profile / "run.json"
    if not path.is_file():
        raise SystemExit(f"{path}: nothing published for profile {profile}")
    record = json.loads(path.read_text())
    record["stale"] = why
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(record, indent=1) + "\n")
    page = path.with_name("README.md")
    text = page.read_text()
    text = re.sub(r"\n> \*\*Stale\*\*:.*\n", "\n", text)
    head, rest = text.split("\n", 1)
    page.write_text(f"{head}\n\n> **Stale**: {why}\n{rest}")
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("."), help="the project folder of the finished run")
    parser.add_argument("--out", type=Path, default=RESULTS, help="where the per-profile folders go")
    parser.add_argument("--mark-stale", metavar="PROFILE", choices=PROFILES, default=None,
                        help="mark a published profile stale instead of publishing (needs --why)")
    parser.add_argument("--why", default=None, help="what changed since the published run")
    args = parser.parse_args(argv)
    if args.mark_stale:
        if not args.why:
            parser.error("--mark-stale needs --why")
        print(f"marked {mark_stale(args.out, args.mark_stale, args.why)} stale")
        return
    out = publish(args.root, args.out)
    print(f"published {out}: " + ", ".join(sorted(p.name for p in out.iterdir())))


if __name__ == "__main__":
    sys.exit(main())
