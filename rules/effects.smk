# The study behind the tables: every variant under every mask model (the rooms' own masks, the other
# `mask_models`, exact object masks = the oracle) and every lift seed, as means with 95 % confidence
# intervals over rooms x seeds, the paired effects of each stage, and the share of the raw-to-oracle
# gap each variant closes (docs/study.md).


rule effects:
    input:
        evals=[r["eval"] for r in effects_spec()["runs"]],
    output:
        table=report(
            f"{RESULTS}/tables/effects.md",
            category="Study",
            caption="../workflow/report/effects.rst",
        ),
        csv=f"{RESULTS}/tables/effects.csv",
        runs=f"{RESULTS}/tables/effects_runs.csv",
        plot=report(
            f"{RESULTS}/plots/effects.png",
            category="Study",
            caption="../workflow/report/effects.rst",
        ),
        masks_plot=report(
            f"{RESULTS}/plots/effects_masks.png",
            category="Study",
            caption="../workflow/report/effects.rst",
        ),
    params:
        spec=lambda w: shlex.quote(json.dumps(effects_spec(), sort_keys=True)),
        code=step_code("effects"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/effects.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} effects --spec {params.spec} --out {output.table:q} --plot {output.plot:q}"
        " > {log:q} 2>&1"
