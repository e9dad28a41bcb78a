# The paper's tables: the main table (registry.yaml's main_table) and every ablation.

rule report_main:
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/report.py"),
        *[P("fvd", name) for name in REG.main_table],
        *[P("probe", target) for target in REG.main_table.values()],
        rules.eval_steering.output.steering,
        rules.eval_speed.output.speed,
        rules.eval_conditioning.output.conditioning,
    output:
        "reports/main_table.csv",
        "reports/steering.csv",
        "reports/speed.csv",
        "reports/conditioning.csv",
        "reports/summary.md",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    log: log("report_main")
    benchmark: bench("report_main")
    shell:
        "python stages/report.py main --profile {params.profile}" + TEE


rule report_all:
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/report.py"),
        *[P("fvd", name) for name in REG.systems],
        *[P("media", name) for name in REG.systems],
        *[P("probe", target) for target in REG.probe_targets],
        rules.eval_steering.output,
        rules.eval_speed.output.speed,
        rules.eval_conditioning.output.conditioning,
    output:
        directory("reports/all"),
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    log: log("report_all")
    benchmark: bench("report_all")
    shell:
        "python stages/report.py all --profile {params.profile}" + TEE
