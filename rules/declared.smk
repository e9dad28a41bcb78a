# The stages made from their declaration alone (orbis2.interfaces, `rules=None`): one rule each, named
# after its kind, every path at its layout path (docs/pipeline.md, "Adding a stage"). The command passes
# every path through params.args and the script through params.script: the loop moves on before a job
# runs (see the Snakefile's _passed_from).

for stage in (s for s in INTERFACES.values() if s.rules is None):
    if stage.launcher != "python" or any(o.named or o.optional for o in stage.paths):
        raise ValueError(f"orbis2.interfaces: {stage.kind} trains or reads a family of entries: "
                         f"give it `rules=` and a rule of its own in rules/*.smk")
    paths = stage_paths(stage, stage.kind)

    rule:
        name: stage.kind
        threads: stage.resources.threads
        priority: stage.priority
        resources: **resources_of(stage)
        input:
            code_inputs(stage.script),
            **inputs(stage, paths),
        output:
            **outputs(stage, paths),
        params:
            **stage_params(stage, paths, script=stage.script, args=shell_args(stage, paths, start=0)),
        log: log(stage.kind)
        benchmark: bench(stage.kind)
        shell:
            "python {params.script} --profile {params.profile}{params.args} 2>&1 | tee {log}"
