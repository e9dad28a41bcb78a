# The paper's tables: the main table (registry.yaml's main_table) and every ablation.

REPORTS = P("reports")  # the main tables' folder
# The records every report reads beside the FVD and probe ones.
RECORD_ARGS = " --steering {input.steering} --speed {input.speed} --conditioning {input.conditioning}"


def report_inputs(systems, targets):
    """The FVD record of each system (inputs fvd_<name>) and the probe record of each target (probe_<name>)."""
    return {**named_inputs("fvd_", "fvd", systems), **named_inputs("probe_", "probe", targets)}


def report_args(systems, targets):
    return named_args("--fvd", "fvd", systems) + named_args("--probe", "probe", targets) + RECORD_ARGS


rule report_main:
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/report.py"),
        **report_inputs(REG.table("main"), REG.table("main").values()),
        steering=rules.eval_steering.output.steering,
        speed=rules.eval_speed.output.speed,
        conditioning=rules.eval_conditioning.output.conditioning,
    output:
        f"{REPORTS}/main_table.csv",
        f"{REPORTS}/steering.csv",
        f"{REPORTS}/speed.csv",
        f"{REPORTS}/conditioning.csv",
        f"{REPORTS}/summary.md",
        f"{REPORTS}/headline.json",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    log: log("report_main")
    benchmark: bench("report_main")
    shell:
        ("python stages/report.py main --profile {params.profile}"
         + report_args(REG.table("main"), REG.table("main").values()) + f" --out {REPORTS}" + TEE)


rule report_all:
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/report.py"),
        **report_inputs(REG.systems, REG.probe_targets),
        **named_inputs("media_", "media", REG.systems),
        steering=rules.eval_steering.output.steering,
        strip=rules.eval_steering.output.strip,
        speed=rules.eval_speed_all.output.speed,
        conditioning=rules.eval_conditioning_all.output.conditioning,
    output:
        report=directory(P("report_all")),
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    log: log("report_all")
    benchmark: bench("report_all")
    shell:
        ("python stages/report.py all --profile {params.profile}" + report_args(REG.systems, REG.probe_targets)
         + named_args("--media", "media", REG.systems) + " --strip {input.strip} --out {output.report}" + TEE)
