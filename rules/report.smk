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
    log:
        f"{RESULTS}/logs/scenes_table.log",
    conda:
        ENV
    shell:
        "trace3d summary {input} --out {output} > {log} 2>&1"
