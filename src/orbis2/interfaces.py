"""One declaration per kind of pipeline stage: the interface its DAG rule and its script share.

A stage's interface is its script, the input and output paths it takes as options
(each at a registry.yaml ``layout`` kind by default), the params.yaml sections it
reads, its machine needs, its scheduling priority and the evaluation record it writes.
The Snakefile builds each rule's named inputs and outputs, ``params:`` sections,
threads, priority, resources and shell options from the declaration, and the stage
script builds its argparse path options and the sections it logs
(:func:`orbis2.stage.open_stage`) from the same object, so the two cannot drift apart.
What varies per registry entry (the predictors a system reads, a predictor's own params
section) stays in the registry and is passed in when a rule is made.

The record is named, not imported: every stage script imports this module, so
importing :mod:`orbis2.eval.records` here would make every stage (the town
included) depend on the record models and re-run when one changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from orbis2.registry import layout_path


@dataclass(frozen=True)
class Resources:
    """A rule's machine needs. threads are capped at --cores, so a rule asking for more than the machine
    has runs alone; gpu, mem_mb and runtime (minutes) are for schedulers (profiles/slurm) and are the
    paper profile's needs. ``nodes``: how many nodes a job spans, each with ``threads``, ``gpu`` and
    ``mem_mb`` (a training job of profiles/slurm, one torchrun per node); Snakemake itself schedules one
    node's worth, so a run on one machine is unaffected."""

    threads: int
    gpu: int
    mem_mb: int
    runtime: int
    nodes: int = 1

    def scheduler(self) -> dict[str, int]:
        """Snakemake's ``resources:`` (everything but threads)."""
        return {"gpu": self.gpu, "mem_mb": self.mem_mb, "runtime": self.runtime}


LIGHT = Resources(threads=1, gpu=0, mem_mb=4000, runtime=60)
CPU = Resources(threads=16, gpu=0, mem_mb=32000, runtime=600)
# The paper's training: 8 nodes of 8 GPUs (64 GPUs; the paper profile's global batches split over them, docs/scale.md).
TRAIN = Resources(threads=16, gpu=8, mem_mb=480000, runtime=2880, nodes=8)
GPU = Resources(threads=16, gpu=1, mem_mb=64000, runtime=600)
# One part of a data stage (orbis2.data.parts): one core, memory bounded by a clip (~0.4 GB measured). At the
# paper's corpus with parts=256, 0.8 M frames a part: about 16 min at the shards' measured 850 frames/s
# (docs/scale.md); the limits leave room for slower disks and fewer parts.
PART = Resources(threads=1, gpu=0, mem_mb=4000, runtime=600)
# One part of the latent cache: one GPU, and cores for the processes that decode shards beside it (all but one,
# orbis2.latents.decode_workers). Memory holds the two encoders and the shards in flight, one per decode worker (a
# 256 MB shard's frames decoded one clip at a time and its latents, about 0.2 GB at the paper profile), whatever
# the corpus.
GPU_PART = Resources(threads=8, gpu=1, mem_mb=32000, runtime=600)
# The latent cache's gather: moves the parts' chunks and writes the tables (the clip table through a memory map),
# with both encoders loaded on the CPU for their latent shapes and normalisation (1 GB of weights at the paper
# profile, twice that while loading).
LATENT_GATHER = Resources(threads=1, gpu=0, mem_mb=8000, runtime=120)
# A frozen network's features and small heads: little memory, but every core. The main target's single
# probe would otherwise run last and alone on one thread (1.8x slower on 2 cores); reports/all's probes
# queue instead of sharing, at the same throughput.
PROBE = Resources(threads=CPU.threads, gpu=LIGHT.gpu, mem_mb=LIGHT.mem_mb, runtime=LIGHT.runtime)


# Which ready job a scheduler starts first (Snakemake's ``priority:``, higher first): the stages other stages
# wait on, then the long evaluations, then the short ones. A run on few cores then ends with short jobs side by
# side instead of one long job alone (the smoke DAG's `reports/all` on 2 cores ran its last FVD stage alone for
# 48 of its 320 s).
FIRST, LONG, SHORT = 2, 1, 0


@dataclass(frozen=True)
class PathOption:
    """One input or output path a stage takes as an option (``--shards DIR``)."""

    key: str  # the rule's named input or output ({input.<key>}); a repeatable one's are <key>_<name>
    option: str  # the script's option
    what: str  # its help text
    layout: str  # the registry.yaml layout kind it lives at
    name: str | None = None  # the layout's {name}: fixed ("town") or the rule's entry ("{name}", "tokenizer_{name}")
    file: str | None = None  # a file inside the layout path
    output: bool = False
    folder: bool = False
    named: bool = False  # repeatable NAME=PATH, one per entry of a family, each at the layout's path for NAME
    optional: bool = False  # the rule passes it for some entries only (a teacher's assets, --init)
    required: bool = False  # the script cannot work it out by itself
    fallback: str | None = None  # the script's own default when left out, where it is not the layout path

    @property
    def per_entry(self) -> bool:
        """The path depends on the rule's entry (or on each NAME): the script works it out after parsing."""
        return self.named or (self.name is not None and "{name}" in self.name)

    def path(self, entry: str | None = None) -> Path:
        """Where the DAG puts it for the rule of ``entry`` (a NAME of a repeatable one)."""
        name = self.name.format(name=entry) if self.name is not None else entry
        path = layout_path(self.layout, name)
        return path / self.file if self.file else path

    def default(self) -> Path | None:
        """The script's default: the layout path where it is the same for every entry, else None."""
        return None if self.per_entry or self.fallback or self.required else self.path()

    def describe_default(self) -> str:
        if self.fallback:
            return self.fallback
        return str(self.path("<name>")) if self.per_entry else str(self.path())


@dataclass(frozen=True)
class Interface:
    """A kind of stage: one script, one or more rules (one per registry entry of a family)."""

    kind: str
    script: str  # relative to the project root
    paths: tuple[PathOption, ...]
    sections: tuple[str, ...]  # params.yaml sections every stage of the kind reads
    resources: Resources
    priority: int  # FIRST, LONG or SHORT
    record: str | None = None  # the orbis2.eval.records model it writes, by name
    rules: str | None = None  # the rules/*.smk file that makes its rules; None: made from this declaration alone
    options: tuple[str, ...] = ()  # options other than paths that its rules pass (how many parts, which one)
    # Its stage runs the training loop (orbis2.train): on Slurm's warning ahead of the time limit it stops at a step
    # boundary with a checkpoint and requeues its job, which profiles/slurm asks for (orbis2.dag.slurm_resources).
    trains: bool = False

    @property
    def launcher(self) -> str:
        """How the rule starts the script: training stages through ``train_launcher`` (torchrun on a node,
        tools/slurm_torchrun.sh over the nodes of a Slurm job)."""
        return "{config[train_launcher]}" if self.resources == TRAIN else "python"

    def option(self, key: str) -> PathOption:
        for option in self.paths:
            if option.key == key:
                return option
        raise KeyError(f"stage {self.kind} declares no path option {key!r} (orbis2.interfaces)")

    def sections_with(self, extra: tuple[str, ...] | list[str] = ()) -> list[str]:
        """The sections a stage of the kind reads, with an entry's own (a predictor's section)."""
        return list(dict.fromkeys([*self.sections, *extra]))


SHARDS = PathOption("shards", "--shards", "shards", "shards", folder=True)
ASSETS = PathOption("assets", "--assets", "pretrained assets (I3D, the teacher, InceptionV3)", "assets",
                    folder=True, fallback="assets.dir")
LATENTS = PathOption("latents", "--latents", "the latent cache", "latents", folder=True,
                     fallback="the latent set's folder, registry.yaml")
TOKENIZERS = tuple(PathOption(f"{level}_tokenizer", f"--{level}-tokenizer", f"the {level} tokenizer's folder "
                              "(its tokenizer.pt)", "tokenizer", folder=True,
                              fallback="the latent set's, registry.yaml") for level in ("detail", "abstract"))
PREDICTORS = PathOption("predictor", "--predictor", "a predictor's folder (its predictor.pt)", "predictor",
                        folder=True, named=True)
REPORT = PathOption("report", "--report", "metrics report", "report", name="{name}", output=True)
TOKENIZER_PATHS = (SHARDS, ASSETS, PathOption("weights", "--out", "output folder", "tokenizer", name="{name}",
                                              output=True, folder=True),
                   PathOption("report", "--report", "metrics report", "report", name="tokenizer_{name}", output=True))


def _declare(*interfaces: Interface) -> dict[str, Interface]:
    return {i.kind: i for i in interfaces}


INTERFACES: dict[str, Interface] = _declare(
    Interface("town", "stages/town.py", (
        PathOption("raw", "--out", "raw episodes folder", "raw", name="town", output=True, folder=True),
        PathOption("sheet", "--sheet", "contact sheet", "reports", file="town_contact_sheet.png", output=True),
        PathOption("preview", "--preview", "preview video", "reports", file="town_preview.mp4", output=True),
    ), ("data", "town"), CPU, FIRST, rules="rules/data.smk",  # the parts too: each renders with a process per core
        options=("--parts", "--part", "--part-manifest")),
    Interface("import", "stages/import.py", (
        PathOption("raw", "--out", "raw episodes folder", "raw", name="import", output=True, folder=True),
    ), ("data", "import"), LIGHT, FIRST, rules="rules/data.smk",  # the gather; the parts run as PART
        options=("--parts", "--part", "--part-manifest")),
    Interface("shards", "stages/shards.py", (
        PathOption("raw", "--raw", "raw episodes folder", "raw", name="{name}", folder=True),
        PathOption("shards", "--out", "shards folder", "shards", output=True, folder=True),
    ), ("data", "shards"), LIGHT, FIRST, rules="rules/data.smk",  # the gather; the parts run as PART
        options=("--parts", "--part", "--part-manifest")),
    Interface("assets", "stages/assets.py", (
        PathOption("assets", "--out", "assets folder", "assets", output=True, folder=True, fallback="assets.dir"),
    ), ("assets",), LIGHT, FIRST, rules="rules/data.smk"),
    # The tokenizers' own sections (tokenizer_<entry>) come with their registry.yaml entry.
    Interface("tokenizer_detail", "stages/tokenizer_detail.py", TOKENIZER_PATHS, ("data",), TRAIN, FIRST,
              rules="rules/tokenizers.smk", trains=True),
    Interface("tokenizer_abstract", "stages/tokenizer_abstract.py", TOKENIZER_PATHS, ("data",), TRAIN, FIRST,
              rules="rules/tokenizers.smk", trains=True),
    Interface("latents", "stages/latents.py", (
        SHARDS, *TOKENIZERS,
        PathOption("latents", "--out", "the latent cache", "latents", name="{name}", output=True, folder=True),
    ), ("data", "latents"), LATENT_GATHER, FIRST, rules="rules/tokenizers.smk",  # the gather; parts: GPU_PART
        options=("--parts", "--part", "--part-manifest")),
    # A predictor's own section (its name) comes with its registry.yaml entry.
    Interface("predictor", "stages/predictor.py", (
        LATENTS, *TOKENIZERS,
        PathOption("init", "--init", "the init_from predictor's folder", "predictor", folder=True, optional=True,
                   fallback="data/predictors/<init_from>"),
        PathOption("weights", "--out", "output folder", "predictor", name="{name}", output=True, folder=True),
        REPORT,
    ), ("data",), TRAIN, FIRST, rules="rules/predictors.smk", trains=True),
    Interface("eval_fvd", "stages/eval_fvd.py", (
        LATENTS, *TOKENIZERS, SHARDS, ASSETS, PREDICTORS,
        PathOption("fvd", "--fvd", "the record", "fvd", name="{name}", output=True),
        PathOption("media", "--media", "sample videos and grid frames", "media", name="{name}", output=True,
                   folder=True),
    ), ("data", "assets", "evaluation"), GPU, LONG, record="FvdRecord", rules="rules/evaluation.smk",
        options=("--parts", "--part", "--part-manifest")),
    Interface("eval_probe", "stages/eval_probe.py", (
        SHARDS, *TOKENIZERS, PathOption("assets", "--assets", "pretrained assets, the teacher", "assets",
                                        folder=True, optional=True, fallback="assets.dir"),
        PREDICTORS, PathOption("probe", "--out", "the record", "probe", name="{name}", output=True),
    ), ("data", "evaluation"), PROBE, SHORT, record="ProbeRecord", rules="rules/evaluation.smk"),
    Interface("inverse_dynamics", "stages/inverse_dynamics.py", (
        SHARDS,
        PathOption("tokenizer", "--tokenizer", "the detail tokenizer's folder, for the reconstructions",
                   "tokenizer", name="detail", folder=True),
        PathOption("weights", "--out", "output folder (its inverse_dynamics.pt)", "inverse_dynamics", output=True,
                   folder=True),
        PathOption("report", "--report", "metrics report", "report", name="inverse_dynamics", output=True),
    ), ("data", "town", "shards", "truth", "inverse_dynamics"), GPU, FIRST, rules="rules/evaluation.smk",
        trains=True),
    # The town's true counterfactuals of the steering starts: data, cached per clip and command.
    Interface("truth", "stages/truth.py", (
        SHARDS,
        PathOption("truth", "--out", "the true counterfactuals' folder", "truth", output=True, folder=True),
        PathOption("report", "--report", "what was rendered and its cost", "report", name="truth", output=True),
    ), ("data", "town", "shards", "evaluation", "truth"), CPU, FIRST),
    Interface("eval_steering", "stages/eval_steering.py", (
        LATENTS, *TOKENIZERS, SHARDS, PREDICTORS, ASSETS,
        PathOption("inverse_dynamics", "--inverse-dynamics", "the learned instrument's folder", "inverse_dynamics",
                   folder=True),
        PathOption("truth", "--truth", "the true counterfactuals' folder", "truth", folder=True),
        PathOption("steering", "--out", "the record", "eval", file="steering.json", output=True),
        PathOption("strip", "--strip", "the figure of one rollout per mode", "eval", file="steering_strip.png",
                   output=True),
        PathOption("headline", "--headline", "the README's figure: one clip, real, reconstructed and rolled out",
                   "eval", file="headline.png", output=True),
    ), ("data", "town", "assets", "evaluation"), GPU, LONG, record="SteeringRecord", rules="rules/evaluation.smk"),
    Interface("eval_speed", "stages/eval_speed.py", (
        LATENTS, *TOKENIZERS, PREDICTORS,
        PathOption("speed", "--out", "the record", "eval", file="speed.json", output=True,
                   fallback="main: reports/eval/speed.json, all: reports/eval/speed_all.json"),
    ), ("data", "evaluation"), GPU, SHORT, record="SpeedRecord", rules="rules/evaluation.smk"),
    Interface("eval_conditioning", "stages/eval_conditioning.py", (
        PathOption("latents", "--latents", "the latent cache", "latents", folder=True,
                   fallback="the compressed latent set's folder, registry.yaml"),
        PREDICTORS,
        PathOption("main_record", "--main-record", "all: the main scope's record, made from the same predictors "
                   "and settings, whose rows it takes for the main predictors instead of evaluating them again",
                   "eval", file="conditioning.json", optional=True, fallback="none: every predictor evaluated"),
        PathOption("conditioning", "--out", "the record", "eval", file="conditioning.json", output=True,
                   fallback="main: reports/eval/conditioning.json, all: reports/eval/conditioning_all.json"),
    ), ("data", "evaluation"), GPU, LONG, record="ConditioningRecord", rules="rules/evaluation.smk"),
    Interface("evaluate", "stages/evaluate.py", (
        PathOption("rollouts", "--rollouts", "the folder of rollouts", "rollouts", name="{name}", folder=True,
                   required=True),
        ASSETS,
        PathOption("instrument", "--instrument", "the learned steering instrument's folder, read when the "
                   "rollouts have trajectories", "inverse_dynamics", folder=True, optional=True),
        *(PathOption(key, f"--{key}", what, "evaluate", name="{name}", file=file, output=True)
          for key, what, file in (("fvd", "the record", "fvd.json"), ("table", "the table and its card", "table.txt"),
                                  ("figure", "the figure", "fvd.png"))),
    ), ("assets", "evaluation", "town"), GPU, LONG, rules="rules/evaluate.smk"),  # a record of `orbis2 evaluate`
    Interface("report", "stages/report.py", (
        PathOption("fvd", "--fvd", "a system's FVD record", "fvd", named=True),
        PathOption("probe", "--probe", "a probe target's record", "probe", named=True),
        *(PathOption(kind, f"--{kind}", f"the {kind} record", "eval", file=f"{kind}.json")
          for kind in ("steering", "speed", "conditioning")),
        PathOption("media", "--media", "a system's media folder (all: the rollout grid)", "media", named=True,
                   folder=True),
        PathOption("strip", "--strip", "the steering strip (all)", "eval", file="steering_strip.png", optional=True),
        PathOption("headline", "--headline", "the headline figure (main)", "eval", file="headline.png",
                   optional=True),
        PathOption("report", "--out", "output folder", "reports", output=True, folder=True,
                   fallback="main: reports, all: reports/all"),
    ), ("data", "evaluation"), LIGHT, SHORT, rules="rules/reports.smk"),
)
