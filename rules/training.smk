# Training: stage 1 (mesh + NeRF), stage 2 (adds the non-rigid deformation and the semantic loss).
# Each stage keeps checkpoint.pt beside its outputs; a rerun after an interruption resumes from it.


rule fetch_perceptual:
    output:
        vgg=PATHS["perceptual_vgg"],
        alex=PATHS["perceptual_alex"],
    params:
        out=lambda w, output: str(Path(output.vgg).parent),
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("fetch_perceptual"),
    shell:
        "delta fetch-perceptual --out {params.out} > {log} 2>&1"


rule train_stage1:
    input:
        record=PATHS["record"],
        init=PATHS["init_params"],
        body=body_model_file(),
    output:
        model=PATHS["stage_model"].replace("{stage}", "1"),
        losses=PATHS["stage_losses"].replace("{stage}", "1"),
    params:
        out=lambda w: PATHS["stage_dir"].format(stage=1, **w),
        preset=training_preset,
        overrides=training_overrides_json,
        device=config["device"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("train_stage1", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("train_stage1", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=train_mem_mb,
        runtime=train_runtime(1),
        **train_gpu_resources(),
    shell:
        "delta train --stage 1 --record {input.record} --body {input.body} --start {input.init}"
        " --out {params.out} --preset {params.preset} --overrides {params.overrides:q}"
        " --device {params.device} --threads {threads} > {log} 2>&1"


rule train_stage2:
    input:
        unpack(stage2_inputs),
        record=PATHS["record"],
        body=body_model_file(),
    output:
        model=PATHS["stage_model"].replace("{stage}", "2"),
        losses=PATHS["stage_losses"].replace("{stage}", "2"),
    params:
        out=lambda w: PATHS["stage_dir"].format(stage=2, **w),
        preset=training_preset,
        overrides=training_overrides_json,
        device=config["device"],
        perceptual=lambda w: str(Path(PATHS["perceptual_vgg"]).parent),
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("train_stage2", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("train_stage2", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=train_mem_mb,
        runtime=train_runtime(2),
        **train_gpu_resources(),
    shell:
        "delta train --stage 2 --record {input.record} --body {input.body} --start {input.stage1}"
        " --out {params.out} --preset {params.preset} --overrides {params.overrides:q}"
        " --perceptual {params.perceptual} --device {params.device} --threads {threads} > {log} 2>&1"
