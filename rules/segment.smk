# Scenes without ground truth (a user's photos or transforms.json, LLFF, a canonical scene without
# instances/): the objects a contrastive lift separates, clustered from its per-Gaussian features with no
# ground truth (trace3d.segment; docs/datasets.md). Scenes with ground truth are scored by rules/evaluate.smk.


rule segment:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=lambda w: gaussians_dir(w.scene, variant(w.variant)),
        lift=f"{RESULTS}/{{scene}}/{{variant}}/lift",
    output:
        # objects/<k>.ply, objects/<k>.png, contact_sheet.png, segment.json
        directory(f"{RESULTS}/{{scene}}/{{variant}}/segment"),
    params:
        p=quoted_params("segment"),
        code=step_code("segment"),
    threads: 2
    resources:
        mem_mb=3000,
        runtime=30,
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/segment.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/segment.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} segment --scene {input.scene:q} --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --lift {input.lift:q} --out {output:q} --params {params.p} > {log:q} 2>&1"


# Every segmented scene's contact sheet (the objects' turntable strips) in the report.
rule segment_pictures:
    localrule: True
    input:
        f"{RESULTS}/{{scene}}/{{variant}}/segment",
    output:
        report(
            f"{RESULTS}/plots/segment/{{scene}}-{{variant}}.png",
            category="Objects (no ground truth)",
            subcategory="{variant}",
            labels={"scene": "{scene}", "variant": "{variant}"},
            caption="../workflow/report/segment.rst",
        ),
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/segment_pictures.log",
    conda:
        ENV
    shell:
        "cp {input:q}/contact_sheet.png {output:q} > {log:q} 2>&1"
