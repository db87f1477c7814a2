# Lifting: contrastive features (or self-prompting settings) per variant, on the variant's labels and Gaussians.
# The variant's `lifting` (contrastive | self_prompt) and `preset` join the scene's `lift` step params.


rule lift:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=lambda w: gaussians_dir(w.scene, variant(w.variant)),
        labels=lift_labels,
    output:
        directory(f"{RESULTS}/{{scene}}/{{variant}}/lift"),
    params:
        p=lift_params,
        labels=lift_labels_arg,
        code=step_code("lift"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=4000,
        runtime=60,
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/lift.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/lift.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} lift --scene {input.scene:q} --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --labels {params.labels:q} --out {output:q} --params {params.p} > {log:q} 2>&1"
