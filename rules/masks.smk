# 2D masks per view (simulated from ground truth | the user's files | SAM | graph | geometry), then
# disjoint patches. The geometry source renders the 2DGS fit, so its masks need the gaussians (and the
# poses they were fitted with); the other sources read the scene only.


rule masks:
    input:
        unpack(mask_inputs),
    output:
        directory(f"{RESULTS}/{{scene}}/masks"),
    params:
        args=mask_args,
        code=step_code("masks"),
    threads: lambda wc: 2 if mask_source(wc) == "sam" else 1
    resources:
        mem_mb=lambda wc: 8000 if mask_source(wc) == "sam" else 1000,
        runtime=lambda wc: 120 if mask_source(wc) == "sam" else 10,
    log:
        f"{RESULTS}/logs/{{scene}}/masks.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/masks.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} masks --scene {input.scene:q} --out {output:q} {params.args} > {log:q} 2>&1"


rule patches:
    input:
        scene=base_folder("scene"),
        masks=f"{RESULTS}/{{scene}}/masks",
    output:
        directory(f"{RESULTS}/{{scene}}/patches"),
    params:
        p=quoted_params("patches"),
        code=step_code("patches"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    log:
        f"{RESULTS}/logs/{{scene}}/patches.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/patches.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} patches --scene {input.scene:q} --masks {input.masks:q} --out {output:q}"
        " --params {params.p} > {log:q} 2>&1"


# Every view's masks painted into one label per pixel (smallest on top): the input of the
# baselines that lift without patches or merging (EgoLifter-style, FlashSplat-style).
rule overlay:
    input:
        scene=base_folder("scene"),
        masks=f"{RESULTS}/{{scene}}/masks",
    output:
        directory(f"{RESULTS}/{{scene}}/overlay"),
    params:
        code=step_code("overlay"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    log:
        f"{RESULTS}/logs/{{scene}}/overlay.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/overlay.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} overlay --scene {input.scene:q} --masks {input.masks:q} --out {output:q} > {log:q} 2>&1"
