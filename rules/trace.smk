# Trace3D's own stages: GIT trace of the raw patches, consistent instance maps, GIT-guided refinement.
# Paths carry only what each step depends on (see the variant notes in rules/common.smk).


rule trace:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=base_folder("gaussians"),
        patches=f"{RESULTS}/{{scene}}/patches",
    output:
        directory(f"{RESULTS}/{{scene}}/trace-{{preset}}"),
    params:
        p=preset_params("trace"),
        code=step_code("trace"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=2000,
        runtime=20,
    log:
        f"{RESULTS}/logs/{{scene}}/trace-{{preset}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/trace-{{preset}}.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} trace --scene {input.scene:q} --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --labels {input.patches:q} --out {output:q} --params {params.p} > {log:q} 2>&1"


rule merge:
    input:
        scene=base_folder("scene"),
        git=f"{RESULTS}/{{scene}}/trace-{{preset}}",
        patches=f"{RESULTS}/{{scene}}/patches",
    output:
        directory(f"{RESULTS}/{{scene}}/merge-{{preset}}"),
    params:
        p=preset_params("merge"),
        code=step_code("merge"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=2000,
        runtime=20,
    log:
        f"{RESULTS}/logs/{{scene}}/merge-{{preset}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/merge-{{preset}}.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} merge --scene {input.scene:q} --git {input.git:q} --patches {input.patches:q}"
        " --out {output:q} --params {params.p} > {log:q} 2>&1"


# The merge's other forms, each in a folder of its own: merge-<preset><mtag>, mtag = -all (variant
# merge_candidates: all_pairs), -hier (merge_method: hierarchical), -released (merge_method: released),
# each optionally followed by -t<threshold> (merge_threshold); rules/common.smk's MERGE_FLAVOURS.
use rule merge as merge_variant with:
    output:
        directory(f"{RESULTS}/{{scene}}/merge-{{preset}}{{mtag}}"),
    params:
        p=merge_tag_params,
        code=step_code("merge"),
    log:
        f"{RESULTS}/logs/{{scene}}/merge-{{preset}}{{mtag}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/merge-{{preset}}{{mtag}}.tsv"


rule refine:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=base_folder("gaussians"),
        labels=refine_labels,
    output:
        directory(f"{RESULTS}/{{scene}}/refine-{{preset}}-{{masks}}"),
    params:
        p=preset_params("refine"),
        labels=refine_labels_arg,
        code=step_code("refine"),
    threads: 1  # same bits at any thread count (TrainParams.grad_buffers); two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=4000,
        runtime=60,
    log:
        f"{RESULTS}/logs/{{scene}}/refine-{{preset}}-{{masks}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/refine-{{preset}}-{{masks}}.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} refine --scene {input.scene:q} --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --labels {params.labels:q} --out {output:q} --params {params.p} > {log:q} 2>&1"
