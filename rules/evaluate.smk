# Evaluation of every (scene, variant): 3D object extraction and novel-view segmentation (Tables 2, 3),
# and the paper-layout tables over all of them (Tables 2, 3, 5). See docs/evaluation.md.
# The lift folder comes from rules/lift.smk (`{RESULTS}/{scene}/{variant}/lift`).
# --label: the variant's name and settings, copied into metrics.json (the tables read them back).
# Two protocols (docs/evaluation.md), both reported: `standard` in <variant>/eval/ (Tables in
# results/tables/), `official` (as the released code evaluates) in <variant>/eval-official/ (Tables in
# results/tables/official/). A scene's `evaluate` params apply to both; the protocol is the rule's.


rule evaluate:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=lambda w: gaussians_dir(w.scene, variant(w.variant)),
        lift=f"{RESULTS}/{{scene}}/{{variant}}/lift",
    output:
        eval=directory(f"{RESULTS}/{{scene}}/{{variant}}/eval"),
        # every evaluated object's Gaussians as a PLY + a turntable picture (docs/evaluation.md)
        objects=directory(f"{RESULTS}/{{scene}}/{{variant}}/objects"),
    params:
        p=evaluate_params("standard"),
        objects=lambda w, output: f"--objects {shlex.quote(output.objects)}",
        label=lambda w: shlex.quote(json.dumps(run_label(w.variant), sort_keys=True)),
        code=step_code("evaluate"),
    threads: 1  # same bits at any thread count; two 1-thread jobs use 2 cores better (docs/performance.md, 'Rule threads')
    resources:
        mem_mb=3000,
        runtime=30,
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/evaluate.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/evaluate.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} evaluate --scene {input.scene:q} --poses {input.poses:q} --gaussians {input.gaussians:q}"
        " --lift {input.lift:q} --out {output.eval:q} {params.objects} --params {params.p} --label {params.label}"
        " > {log:q} 2>&1"


use rule evaluate as evaluate_official with:
    output:
        eval=directory(f"{RESULTS}/{{scene}}/{{variant}}/eval-official"),
    params:
        p=evaluate_params("official"),
        objects="",
        label=lambda w: shlex.quote(json.dumps(run_label(w.variant), sort_keys=True)),
        code=step_code("evaluate"),
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/evaluate-official.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/evaluate-official.tsv"


# NVOS (paper Table 4): the scribbles select instances of the variant's reference-view map; the lifted
# query gives the target view's mask (docs/evaluation.md, NVOS).
rule evaluate_nvos:
    input:
        scene=base_folder("scene"),
        poses=base_folder("poses"),
        gaussians=lambda w: gaussians_dir(w.scene, variant(w.variant)),
        lift=f"{RESULTS}/{{scene}}/{{variant}}/lift",
        labels=lift_labels,
    output:
        directory(f"{RESULTS}/{{scene}}/{{variant}}/eval-nvos"),
    params:
        labels=lift_labels_arg,
        label=lambda w: shlex.quote(json.dumps(run_label(w.variant), sort_keys=True)),
        code=step_code("evaluate-nvos"),
    threads: 2
    resources:
        mem_mb=3000,
        runtime=30,
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/evaluate-nvos.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/evaluate-nvos.tsv"
    conda:
        ENV
    shell:
        "trace3d --threads {threads} evaluate-nvos --scene {input.scene:q} --poses {input.poses:q}"
        " --gaussians {input.gaussians:q} --lift {input.lift:q} --labels {params.labels:q} --out {output:q}"
        " --label {params.label} > {log:q} 2>&1"


TABLES = ("table2", "table2_psnr", "table3", "table5")


rule tables:
    input:
        expand(f"{RESULTS}/{{scene}}/{{variant}}/eval", scene=EVAL_SCENES, variant=list(VARIANTS)),
    output:
        **{
            t: report(
                f"{RESULTS}/tables/{t}.md",
                category="Tables",
                caption=f"../workflow/report/{t}.rst",
            )
            for t in TABLES
        },
        **{f"{t}_{ext}": f"{RESULTS}/tables/{t}.{ext}" for t in TABLES for ext in ("csv", "tex")},
    params:
        results=lambda w, output: os.path.dirname(os.path.dirname(output.table2)),
        out=lambda w, output: os.path.dirname(output.table2),
        code=step_code("tables"),
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    log:
        f"{RESULTS}/logs/tables.log",
    conda:
        ENV
    shell:
        "trace3d --threads {threads} tables --results {params.results:q} --out {params.out:q} --evals {input:q} > {log:q} 2>&1"


# Tables 2, 3 and 5 of the paper's own rows alone (config `paper_rows`; results/tables/paper/), built by target
# paper_tables before the jobs of the variants beyond the paper: what `make reproduce` shows first.
use rule tables as tables_paper_rows with:
    input:
        expand(f"{RESULTS}/{{scene}}/{{variant}}/eval", scene=EVAL_SCENES, variant=PAPER_ROWS),
    output:
        **{
            t: report(
                f"{RESULTS}/tables/paper/{t}.md",
                category="Tables (the paper's rows, written first)",
                caption=f"../workflow/report/{t}.rst",
            )
            for t in TABLES
        },
        **{f"{t}_{ext}": f"{RESULTS}/tables/paper/{t}.{ext}" for t in TABLES for ext in ("csv", "tex")},
    params:
        results=lambda w, output: os.path.dirname(os.path.dirname(os.path.dirname(output.table2))),
        out=lambda w, output: os.path.dirname(output.table2),
        code=step_code("tables"),
    log:
        f"{RESULTS}/logs/tables-paper.log",


# Table 4 from the NVOS scenes (results/tables/table4.*).
use rule tables as tables_nvos with:
    input:
        expand(f"{RESULTS}/{{scene}}/{{variant}}/eval-nvos", scene=NVOS_SCENES, variant=list(VARIANTS)),
    output:
        table4=report(
            f"{RESULTS}/tables/table4.md",
            category="Tables",
            caption="../workflow/report/table4.rst",
        ),
        table4_csv=f"{RESULTS}/tables/table4.csv",
        table4_tex=f"{RESULTS}/tables/table4.tex",
    params:
        results=lambda w, output: os.path.dirname(os.path.dirname(output.table4)),
        out=lambda w, output: os.path.dirname(output.table4),
        code=step_code("tables"),
    log:
        f"{RESULTS}/logs/tables-nvos.log",


# The same tables under the official protocol (results/tables/official/).
use rule tables as tables_official with:
    input:
        expand(f"{RESULTS}/{{scene}}/{{variant}}/eval-official", scene=EVAL_SCENES, variant=list(VARIANTS)),
    output:
        **{
            t: report(
                f"{RESULTS}/tables/official/{t}.md",
                category="Tables (official protocol)",
                caption=f"../workflow/report/{t}.rst",
            )
            for t in TABLES
        },
        **{f"{t}_{ext}": f"{RESULTS}/tables/official/{t}.{ext}" for t in TABLES for ext in ("csv", "tex")},
    params:
        results=lambda w, output: os.path.dirname(os.path.dirname(os.path.dirname(output.table2))),
        out=lambda w, output: os.path.dirname(output.table2),
        code=step_code("tables"),
    log:
        f"{RESULTS}/logs/tables-official.log",


# The evaluation figure of every (scene, variant), beside the tables in the report.
rule evaluation_pictures:
    localrule: True
    input:
        f"{RESULTS}/{{scene}}/{{variant}}/eval",
    output:
        report(
            f"{RESULTS}/plots/evaluation/{{scene}}-{{variant}}.png",
            category="Evaluation",
            subcategory="{variant}",
            labels={"scene": "{scene}", "variant": "{variant}"},
            caption="../workflow/report/evaluation.rst",
        ),
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/evaluation_pictures.log",
    conda:
        ENV
    shell:
        "cp {input:q}/pictures.png {output:q} > {log:q} 2>&1"


# The feature PCA of every contrastive lift (rendered test views), beside the evaluation figures.
rule lift_pictures:
    localrule: True
    input:
        f"{RESULTS}/{{scene}}/{{variant}}/lift",
    output:
        report(
            f"{RESULTS}/plots/lift/{{scene}}-{{variant}}.png",
            category="Lifting",
            subcategory="{variant}",
            labels={"scene": "{scene}", "variant": "{variant}"},
            caption="../workflow/report/lift.rst",
        ),
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/lift_pictures.log",
    conda:
        ENV
    shell:
        "cp {input:q}/pca.png {output:q} > {log:q} 2>&1"
