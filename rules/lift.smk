# Lifting: contrastive features (or self-prompting settings) per variant, on the variant's labels and Gaussians.
# The variant's `lifting` (contrastive | self_prompt) and `preset` join the scene's `lift` step params.


def lift_labels(wildcards):
    return labels_dir(wildcards.scene, variant(wildcards.variant))


def lift_labels_arg(wildcards):
    """The instance maps themselves: a merge folder keeps them in instances/, the patches folder is the maps."""
    v = variant(wildcards.variant)
    folder = labels_dir(wildcards.scene, v)
    return f"{folder}/instances" if v["consistent_masks"] else folder


def lift_params(wildcards):
    v = variant(wildcards.variant)
    merged = json.loads(step_params(wildcards.scene, "lift"))
    merged["method"] = v["lifting"]
    merged.setdefault("preset", v["preset"])
    if v["lifting"] == "self_prompt":  # contrastive-only keys of a shared `lift` block do not apply
        for key in LIFT_CONTRASTIVE_ONLY:
            merged.pop(key, None)
    else:
        for key in LIFT_SELF_PROMPT_ONLY:
            merged.pop(key, None)
    return shlex.quote(json.dumps(merged, sort_keys=True))


LIFT_CONTRASTIVE_ONLY = ("dim", "kernel", "temperature", "temperature_pos", "temperature_neg", "lr", "iterations",
                         "pixels", "pool_pixels", "init_std", "path", "pca_views", "log_every", "query")
LIFT_SELF_PROMPT_ONLY = ("prompt_source", "simulate", "sam_checkpoint", "sam_model_type", "sam_device", "points",
                         "max_views", "gaussian_share", "mask_threshold", "min_prompt_pixels")


rule lift:
    input:
        scene=f"{RESULTS}/{{scene}}/scene",
        poses=f"{RESULTS}/{{scene}}/poses",
        gaussians=lambda w: gaussians_dir(w.scene, variant(w.variant)),
        labels=lift_labels,
    output:
        directory(f"{RESULTS}/{{scene}}/{{variant}}/lift"),
    params:
        p=lift_params,
        labels=lift_labels_arg,
        code=code_version("scene.py", "render", "gaussians.py", "lifting", "masks", "tracing/git.py"),
    threads: 2
    resources:
        mem_mb=6000,
    log:
        f"{RESULTS}/logs/{{scene}}/{{variant}}/lift.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{scene}}/{{variant}}/lift.tsv"
    conda:
        ENV
    shell:
        "trace3d lift --scene {input.scene} --poses {input.poses} --gaussians {input.gaussians}"
        " --labels {params.labels} --out {output} --params {params.p} > {log} 2>&1"
