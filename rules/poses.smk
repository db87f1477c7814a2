# Step 2: camera poses by pycolmap structure-from-motion, or the data set's own (`poses: {mode: dataset}`).


rule poses:
    wildcard_constraints:
        scene=BASE_SCENE_PATTERN,
    input:
        f"{RESULTS}/{{scene}}/scene",
    output:
        directory(f"{RESULTS}/{{scene}}/poses"),
    params:
        p=quoted_params("poses"),
        code=step_code("poses"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=2000,
        runtime=30,
    log:
        f"{RESULTS}/logs/{{scene}}/poses.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/poses.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} poses --scene {input:q} --out {output:q} --params {params.p} > {log:q} 2>&1"
