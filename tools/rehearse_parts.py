"""Rehearse the data path in parts on a Slurm cluster: many short town episodes through the town, the shards and
the latent cache at ``--parts N``, submitted through profiles/slurm-local (one Slurm job per part, or with
``--arrays`` one array per stage), with one part of the town killed (SIGKILL, ``scancel --signal=KILL --full``)
in the middle and the run started again.

    tools/slurm_local.sh start          # a one-node cluster on this machine (or run it on yours)
    python tools/rehearse_parts.py --dir /tmp/rehearsal --json rehearsal.json

What it checks and reports (``--json``):

- the Slurm arrays submitted (with ``--arrays``: the executor plugin's ``--slurm-array-jobs`` for the parts'
  rules). In snakemake-executor-plugin-slurm 2.8.0 (with the jobstep plugin 0.6.1) an array's tasks after the
  first run their own part, but the Snakemake around each of them takes it for the first task's job: it
  removes that job's output before it starts and fails for want of it when done (the plugin's issue 447), so
  such a run fails; without ``--arrays`` every part is its own Slurm job;
- the killed part, started again, renders only the episodes it had not logged: its ``done.jsonl`` holds each
  of its episodes once (the count at the kill, and the count after);
- the town, the shards' samples and the latent chunks equal, byte for byte, what one part writes (built here
  with the library, ``parts=1``), compared by SHA-256 digests.

The corpus: the smoke profile with ``--train`` train episodes of 3 s and the other splits' smoke lengths (216
episodes by default), in a copy of this checkout's tracked files (with their edits) under ``--dir``, whose code
the jobs run. Needs Slurm's client tools (``sinfo``, ``scancel``) and
``snakemake-executor-plugin-slurm``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
KILLED_STAGE = "town"  # the stage whose part is killed: one log line per episode, so the counts say what was redone
ARRAY_RULES = ("town_part", "shards_part", "latents_part")


def project_copy(dest: Path, episodes: dict[str, int]) -> Path:
    """This checkout's tracked files as they are now (edits included: ``git stash create``; files not yet added
    are left out) in ``dest`` (a new git repo), at the smoke profile with ``episodes`` town episodes per split."""
    tree = subprocess.run(["git", "stash", "create"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip() or "HEAD"
    dest.mkdir(parents=True)
    archive = subprocess.run(["git", "archive", tree], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    params = yaml.safe_load((dest / "params.yaml").read_text())
    params["profile"] = "smoke"
    params["town"]["smoke"].update(episodes=episodes, turns_candidates=2 * episodes["turns"])
    params["town"]["smoke"]["episode_seconds"]["train"] = params["shards"]["smoke"]["clip_seconds"]["train"]
    (dest / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "rehearsal"]):
        subprocess.run(cmd, cwd=dest, check=True, capture_output=True)
    return dest


def snakemake(project: Path, parts: int, log: Path, env: dict[str, str], arrays: bool) -> subprocess.Popen:
    """The DAG up to the latent cache through the Slurm profile, the parts side by side (``--jobs`` and ``--cores``
    above the parts: the plugin submits an array once every part of a rule is handed to it)."""
    cmd = [sys.executable, "-m", "snakemake", "--profile", str(ROOT / "profiles/slurm-local"), "data/latents",
           "--jobs", str(4 * parts), "--cores", str(16 * parts), "--rerun-incomplete", "--config", "profile=smoke",
           f"parts={parts}"]
    cmd += ["--slurm-array-jobs", ",".join(ARRAY_RULES)] if arrays else []
    return subprocess.Popen(cmd, cwd=project, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


def jobs(log_text: str) -> int:
    """How many Slurm jobs (an array counts once) the run submitted."""
    return len(re.findall(r"submitted with SLURM jobid|Submitted array job with", log_text))


def part_process(project: Path, stage_script: str, part: int, parts: int) -> int | None:
    """The pid of the stage process of part ``part`` running in ``project`` (read from /proc), None if none."""
    want = [stage_script, "--parts", str(parts), "--part", str(part)]
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            args = (proc / "cmdline").read_bytes().split(b"\0")
            cwd = os.readlink(proc / "cwd")
        except OSError:
            continue
        words = [a.decode(errors="replace") for a in args if a]
        if cwd == str(project) and all(w in words for w in want) and words[words.index("--part") + 1] == str(part):
            return int(proc.name)
    return None


def slurm_job_of(pid: int) -> str:
    """``<array job>_<task>`` (or the job id) of the Slurm job running ``pid``, from its environment."""
    env = dict(item.split(b"=", 1) for item in (Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")) if b"=" in item)
    if b"SLURM_ARRAY_JOB_ID" in env:
        return f"{env[b'SLURM_ARRAY_JOB_ID'].decode()}_{env[b'SLURM_ARRAY_TASK_ID'].decode()}"
    return env[b"SLURM_JOB_ID"].decode()


def log_lines(project: Path, stage: str, part: int, parts: int) -> list[dict]:
    """The events of a part's ``done.jsonl`` (its work folder: data/runs/<stage>-smoke-<key>/<part>/)."""
    name = f"{part:04d}-of-{parts:04d}"
    logs = sorted((project / "data/runs").glob(f"{stage}-smoke-*/{name}/done.jsonl"))
    return [json.loads(line) for line in logs[0].read_text().splitlines()] if logs else []


def kill_a_part(project: Path, run: subprocess.Popen, parts: int, after: int) -> dict:
    """Wait until part ``parts // 2`` of the town has logged ``after`` episodes, then kill its Slurm job (SIGKILL to
    every process of it); return what was logged at the kill."""
    part = parts // 2
    while run.poll() is None:
        if len(log_lines(project, KILLED_STAGE, part, parts)) >= after:
            pid = part_process(project, f"stages/{KILLED_STAGE}.py", part, parts)
            if pid is not None:
                job = slurm_job_of(pid)
                subprocess.run(["scancel", "--signal=KILL", "--full", job], check=True)
                time.sleep(2)
                return {"stage": KILLED_STAGE, "part": part, "slurm_job": job,
                        "logged_at_kill": len(log_lines(project, KILLED_STAGE, part, parts))}
        time.sleep(0.5)
    raise RuntimeError("the run ended before the part to kill had logged enough episodes")


def arrays(log_text: str) -> list[dict]:
    """The array submissions the executor plugin logged."""
    found = re.findall(r"Submitted array job with Snakemake IDs ([\d,]+) and SLURM job ID (\d+)\. "
                       r"The individual task IDs are (\d+)-(\d+)", log_text)
    return [{"slurm_job": job, "tasks": int(last) - int(first) + 1, "snakemake_jobs": len(ids.split(","))}
            for ids, job, first, last in found]


def digest(pairs) -> str:
    h = hashlib.sha256()
    for name, data in pairs:
        h.update(name.encode() + b"\0" + hashlib.sha256(data).digest())
    return h.hexdigest()


def files_digest(root: Path, skip: tuple[str, ...] = ()) -> str:
    """SHA-256 over every file under ``root`` (relative path and bytes), in path order, but Snakemake's marker of a
    folder output (``.snakemake_timestamp``) and ``skip``."""
    return digest((p.relative_to(root).as_posix(), p.read_bytes()) for p in sorted(root.rglob("*"))
                  if p.is_file() and p.name not in (".snakemake_timestamp", *skip))


def samples_digest(shards: Path) -> str:
    """SHA-256 over every sample of every split's shards, in manifest order (where shards end does not count)."""
    manifest = json.loads((shards / "manifest.json").read_text())

    def members():
        for split in sorted(manifest["splits"]):
            for shard in manifest["splits"][split]["shards"]:
                with tarfile.open(shards / shard["path"]) as tar:
                    for member in tar:
                        yield f"{split}/{member.name}", tar.extractfile(member).read()

    return digest(members())


def one_part(project: Path, out: Path) -> dict[str, str]:
    """The town, shards and latent cache that one part writes, from the same settings and tokenizers, built here
    with the library; their digests."""
    sys.path.insert(0, str(project / "src"))  # the copy's code, as the jobs ran it
    from orbis2.config.params import load_config
    from orbis2.data.shards import write_shards
    from orbis2.data.town_dataset import build_town_dataset
    from orbis2.latents import build_latent_cache
    from orbis2.stage import TOKENIZER_FILE

    os.chdir(project)  # the cache's meta.json names its shards and tokenizers as the stage does, relative to it
    cfg = load_config("params.yaml", "smoke")
    build_town_dataset(out / "town", cfg.data, cfg.town)
    write_shards(out / "town", out / "shards", cfg.data, cfg.shards)
    splits = list(json.loads((out / "shards/manifest.json").read_text())["splits"])
    tokenizers = [Path("data/tokenizers") / level / TOKENIZER_FILE for level in ("detail", "abstract")]
    build_latent_cache(Path("data/shards"), out / "latents", *tokenizers, cfg.latents.batch_size, splits)
    return {"town": files_digest(out / "town"), "shards": samples_digest(out / "shards"),
            "latents": files_digest(out / "latents")}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, required=True, help="an empty or new folder every node sees")
    parser.add_argument("--parts", type=int, default=4)
    parser.add_argument("--train", type=int, default=160, help="train episodes of 3 s (default: 160)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument("--arrays", action="store_true",
                        help="submit the parts as Slurm arrays (--slurm-array-jobs; fails with plugin 2.8.0, above)")
    args = parser.parse_args(argv)
    if args.dir.exists() and any(args.dir.iterdir()):
        parser.error(f"--dir {args.dir}: not empty; give a new folder")
    if shutil.which("sinfo") is None or subprocess.run(["sinfo", "-h"], capture_output=True).returncode != 0:
        sys.exit("rehearse_parts: no Slurm cluster answers `sinfo`; start one: tools/slurm_local.sh start")
    episodes = {"train": args.train, "val": 24, "turns": 8, "heldout": 16, "probe": 8}
    project = project_copy(args.dir.resolve() / "project", episodes)
    # The copy's code, not this checkout's: an edit here while the jobs run would change the parts' resume key.
    os.environ["OMP_NUM_THREADS"] = "1"
    env = {**os.environ, "PYTHONPATH": str(project / "src"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{project / 'mlflow.db'}"}
    env.pop("ORBIS2_PIPELINE_ID", None)
    total, part = sum(episodes.values()), args.parts // 2
    per_part = total * (part + 1) // args.parts - total * part // args.parts  # the killed part's (parts.part_slice)

    started = time.perf_counter()
    first = snakemake(project, args.parts, args.dir / "run1.log", env, args.arrays)
    killed = kill_a_part(project, first, args.parts, after=per_part // 3)
    first.wait()
    second = snakemake(project, args.parts, args.dir / "run2.log", env, args.arrays)
    if second.wait() != 0:
        sys.exit(f"rehearse_parts: the second run failed; see {args.dir / 'run2.log'}")
    wall = time.perf_counter() - started
    events = log_lines(project, KILLED_STAGE, killed["part"], args.parts)
    stems = [e["record"]["stem"] for e in events]
    killed.update(episodes_in_part=per_part, logged_after_resume=len(events), distinct_after_resume=len(set(stems)),
                  rendered_after_resume=len(events) - killed["logged_at_kill"])

    slurm = {run: {"jobs": jobs(text), "arrays": arrays(text)}
             for run, text in ((r, (args.dir / f"{r}.log").read_text()) for r in ("run1", "run2"))}
    theirs = {"town": files_digest(project / "data/raw/town", skip=("motion.json",)),  # the gather's statistics
              "shards": samples_digest(project / "data/shards"), "latents": files_digest(project / "data/latents")}
    ours = one_part(project, args.dir.resolve() / "one_part")
    result = {"parts": args.parts, "episodes": total,
              "frames": sum(e["frames"] for e in json.loads((project / "data/raw/town/index.json").read_text())
                            ["episodes"]),
              "wall_s_both_runs": round(wall), "killed": killed, "slurm": slurm,
              "digests": {k: {"parts": theirs[k], "one_part": ours[k], "equal": theirs[k] == ours[k]} for k in ours}}
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    ok = all(d["equal"] for d in result["digests"].values()) and killed["distinct_after_resume"] == per_part \
        and killed["logged_after_resume"] == per_part
    if not ok:
        sys.exit("rehearse_parts: the parts differ from one part, or the killed part redid finished episodes")
    return result


if __name__ == "__main__":
    main()
