# Step 3: fit a 2D Gaussian Splatting scene to the training views (poses from the `poses` step).


rule gaussians:
    wildcard_constraints:
        scene=FIT_SCENE_PATTERN,  # the configured scenes and their fit seeds (<room>.fit<seed>)
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
    output:
        directory(f"{RESULTS}/{{scene}}/gaussians"),
    params:
        p=quoted_params("gaussians"),
        code=step_code("gaussians"),
    threads: 1  # same bits at any thread count (TrainParams.grad_buffers); two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=4000,
        runtime=60,
    log:
        f"{RESULTS}/logs/{{scene}}/gaussians.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/gaussians.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} gaussians --scene {input.scene:q} --poses {input.poses:q} --out {output:q}"
        " --params {params.p} > {log:q} 2>&1"
