# Step 1: the canonical scene folder, generated (synthetic benchmark) or imported (Replica, NVOS, LLFF).


rule scene:
    wildcard_constraints:
        scene=BASE_SCENE_PATTERN,
    output:
        directory(f"{RESULTS}/{{scene}}/scene"),
    params:
        args=scene_kind_args,
        code=step_code("scene"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=1000,
        runtime=15,
    log:
        f"{RESULTS}/logs/{{scene}}/scene.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/scene.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} scene {params.args} --out {output:q} > {log:q} 2>&1"
