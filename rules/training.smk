# Training: stage 1 (mesh + NeRF), stage 2 (adds the non-rigid deformation and the semantic loss).
# One rule over {stage}: each stage's params hold only the settings that stage reads, so a change to
# stage 2's settings reruns stage 2 alone. Each stage keeps checkpoint.pt beside its outputs; a rerun
# after an interruption resumes from it, and one whose last step is done writes it out.


rule fetch_perceptual:
    output:
        vgg=PATHS["perceptual_vgg"],
        alex=PATHS["perceptual_alex"],
    log:
        log_path("fetch_perceptual"),
    conda:
        "../workflow/envs/delta.yaml"
    params:
        out=lambda w, output: str(Path(output.vgg).parent),
    shell:
        "delta fetch-perceptual --out {params.out:q} > {log:q} 2>&1"


rule train:
    input:
        unpack(train_inputs),
    output:
        model=PATHS["stage_model"],
        losses=PATHS["stage_losses"],
    log:
        log_path("train", "{dataset}_{subject}_stage{stage}"),
    benchmark:
        benchmark_path("train", "{dataset}_{subject}_stage{stage}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        **train_gpu_resources(),
        mem_mb=train_mem_mb,
        runtime=train_runtime,
    params:
        out=lambda w: PATHS["stage_dir"].format(**w),
        settings=stage_training,
        device=config["device"],
        perceptual=lambda w: str(Path(PATHS["perceptual_vgg"]).parent),
    shell:
        "delta train --stage {wildcards.stage:q} --record {input.record:q} --body {input.body:q} --start {input.start:q}"
        " --out {params.out:q} --settings {params.settings:q} --scene {input.scene:q}"
        " --perceptual {params.perceptual:q} --device {params.device:q} --threads {threads} > {log:q} 2>&1"
