# The paper's tables: the main table (registry.yaml's main_table) and every ablation.

REPORT = INTERFACES["report"]
REPORT_MAIN = stage_paths(REPORT, fvd=REG.table("main"), probe=REG.table("main").values(),
                          headline=rules.eval_steering.output.headline, report=P("reports"))
REPORT_ALL = stage_paths(REPORT, fvd=REG.systems, probe=REG.probe_targets, media=REG.systems,
                         speed=rules.eval_speed_all.output.speed, strip=rules.eval_steering.output.strip,
                         conditioning=rules.eval_conditioning_all.output.conditioning, report=P("report_all"))


rule report_main:
    threads: REPORT.resources.threads
    priority: REPORT.priority
    resources: **resources_of(REPORT)
    input:
        code_inputs(REPORT.script),
        **inputs(REPORT, REPORT_MAIN),
    output:  # the main tables' files in the folder passed as --out
        *(f"{REPORT_MAIN['report']}/{name}" for name in ("main_table.csv", "steering.csv", "speed.csv",
                                                      "conditioning.csv", "summary.md", "headline.json",
                                                      "intervals.csv", "intervals.png", "headline.png")),
    params:
        **stage_params(REPORT, REPORT_MAIN),
    log: log("report_main")
    benchmark: bench("report_main")
    shell:
        command(REPORT, head=" main")


rule report_all:
    threads: REPORT.resources.threads
    priority: REPORT.priority
    resources: **resources_of(REPORT)
    input:
        code_inputs(REPORT.script),
        **inputs(REPORT, REPORT_ALL),
    output:
        **outputs(REPORT, REPORT_ALL),
    params:
        **stage_params(REPORT, REPORT_ALL),
    log: log("report_all")
    benchmark: bench("report_all")
    shell:
        command(REPORT, head=" all")
