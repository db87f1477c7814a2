# The robustness curve (beyond the paper): object / NVS mIoU of some variants as the simulated masks'
# inconsistency rises, on the rooms of `robustness.scenes` (derived scenes <room>@inc<level> share the
# room's scene, poses and 2DGS fit: see rules/common.smk). docs/robustness.md.


rule robustness:
    input:
        evals=[r["eval"] for r in robustness_spec()["runs"]],
        merges=[m["merge"] for m in robustness_spec()["merges"]],
    output:
        table=report(
            f"{RESULTS}/tables/robustness.md",
            category="Robustness",
            caption="../workflow/report/robustness.rst",
        ),
        csv=f"{RESULTS}/tables/robustness.csv",
        plot=report(
            f"{RESULTS}/plots/robustness.png",
            category="Robustness",
            caption="../workflow/report/robustness.rst",
        ),
    params:
        spec=lambda w: shlex.quote(json.dumps(robustness_spec(), sort_keys=True)),
        code=step_code("robustness"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/robustness.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} robustness --spec {params.spec} --out {output.table:q} --plot {output.plot:q}"
        " > {log:q} 2>&1"
