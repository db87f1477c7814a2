# trace3d: Trace3D (ICCV 2025) as a cached, per-scene Snakemake pipeline.
#   snakemake --cores 2 reproduce                        # everything in config/config.yaml
#   snakemake --cores 2 results/room1/gaussians          # one scene, up to its 2DGS fit
#   snakemake --cores 2 --forcerun=gaussians results/room1/gaussians   # rerun that step
#   snakemake --cores 2 --configfile=my.yaml reproduce   # `=`: --configfile/--config/--forcerun take several values
from snakemake.utils import min_version

min_version("9.0")


# The default benchmark, unless the user gave a config of their own (--configfile replaces it
# instead of being merged into it, so a user's scene list is exactly theirs).
if not config:

    configfile: "config/config.yaml"


include: "rules/common.smk"
include: "rules/scene.smk"
include: "rules/poses.smk"
include: "rules/masks.smk"
include: "rules/gaussians.smk"
include: "rules/trace.smk"
include: "rules/lift.smk"
include: "rules/evaluate.smk"
include: "rules/segment.smk"
include: "rules/report.smk"
include: "rules/robustness.smk"
include: "rules/effects.smk"


# A local run needs no job-rate limiter (the cores bound the job starts), and Snakemake's keeps one
# re-evaluation timer per finished job alive (trace3d/tooling/scheduling.py); on a cluster it stays.
onstart:
    from trace3d.tooling.scheduling import unthrottle_local

    _line = unthrottle_local(workflow)
    if _line:
        logger.info(_line)


rule reproduce:
    default_target: True
    input:
        f"{RESULTS}/scenes.md",
        expand(f"{RESULTS}/{{scene}}/patches", scene=SCENES),
        f"{RESULTS}/reconstruction.md",
        [d for s in SCENES for v in VARIANTS.values() for d in variant_outputs(s, v)],
        f"{RESULTS}/tracing.md" if table_variant() is not None else [],
        # every variant lifted on every scene; scored (Tables 2, 3, 5) where the scene has ground truth
        expand(f"{RESULTS}/{{scene}}/{{variant}}/lift", scene=SCENES, variant=list(VARIANTS)),
        rules.tables.output if EVAL_SCENES else [],
        rules.tables_paper_rows.output if EVAL_SCENES else [],
        rules.tables_official.output if EVAL_SCENES else [],
        rules.tables_nvos.output if NVOS_SCENES else [],
        expand(f"{RESULTS}/plots/evaluation/{{scene}}-{{variant}}.png", scene=EVAL_SCENES, variant=list(VARIANTS)),
        [f"{RESULTS}/plots/lift/{s}-{n}.png" for s in SCENES for n, v in VARIANTS.items() if v["lifting"] == "contrastive"],
        # scenes without ground truth: the objects the contrastive lift separates (PLYs, turntables, contact sheet)
        [f"{RESULTS}/plots/segment/{s}-{n}.png" for s in SEGMENT_SCENES for n, v in VARIANTS.items()
         if v["lifting"] == "contrastive"],
        # object / NVS mIoU against the simulated mask inconsistency (config `robustness`)
        rules.robustness.output if ROBUSTNESS.get("scenes") else [],
        # the other mask models, the oracle and the lift seeds (config `mask_models`, `oracle`, `seeds`):
        # every run lifted, scored where the room has ground truth, and the effects table over all of them
        [f"{RESULTS}/{s}/{r}/lift" for s, r in scene_runs()],
        rules.effects.output if effects_spec()["runs"] else [],


# The paper's tables first: Tables 2, 3 and 5 of the paper's own rows (config `paper_rows`, default every
# variant) at lift seed 0, standard protocol (results/tables/paper/), with the scene, reconstruction and
# tracing tables they need no extra job for. `make reproduce` builds this target before `reproduce`, so the
# tables are on screen before the variants beyond the paper and the study's rows (mask models, oracle, seeds,
# robustness) and the official protocol run; `trace3d progress` says where a run is.
rule paper_tables:
    input:
        f"{RESULTS}/scenes.md",
        f"{RESULTS}/reconstruction.md",
        f"{RESULTS}/tracing.md" if table_variant() is not None else [],
        rules.tables_paper_rows.output if EVAL_SCENES else [],
