# Aggregation: the tables the `reproduce` target produces.


rule scenes_table:
    input:
        expand(f"{RESULTS}/{{scene}}/scene", scene=SCENES),
    output:
        report(
            f"{RESULTS}/scenes.md",
            category="Scenes",
            caption="../workflow/report/scenes.rst",
        ),
    params:
        code=step_code("summary"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/scenes_table.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} summary {input:q} --out {output:q} > {log:q} 2>&1"


rule reconstruction_table:
    input:
        poses=expand(f"{RESULTS}/{{scene}}/poses", scene=SCENES),
        gaussians=expand(f"{RESULTS}/{{scene}}/gaussians", scene=SCENES),
    output:
        table=report(
            f"{RESULTS}/reconstruction.md",
            category="Reconstruction",
            caption="../workflow/report/reconstruction.rst",
        ),
        plot=report(
            f"{RESULTS}/plots/reconstruction.png",
            category="Reconstruction",
            caption="../workflow/report/reconstruction.rst",
        ),
    params:
        code=step_code("reconstruction-table"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/reconstruction_table.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} reconstruction-table --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --out {output.table:q} --plot {output.plot:q} > {log:q} 2>&1"


rule tracing_table:
    input:
        merge=lambda wc: [f"{RESULTS}/{s}/merge-{table_variant()['preset']}" for s in SCENES],
        refine=lambda wc: [gaussians_dir(s, table_variant()) for s in SCENES],
    output:
        table=report(
            f"{RESULTS}/tracing.md",
            category="Tracing",
            caption="../workflow/report/tracing.rst",
        ),
        plot=report(
            f"{RESULTS}/plots/merge.png",
            category="Tracing",
            caption="../workflow/report/tracing.rst",
        ),
    params:
        code=step_code("tracing-table"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/tracing_table.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} tracing-table --merge {input.merge:q} --refine {input.refine:q}"
        " --out {output.table:q} --plot {output.plot:q} > {log:q} 2>&1"
