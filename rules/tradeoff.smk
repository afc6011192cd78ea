# The speed/accuracy sweep: results/{dataset}/tradeoff.csv and tradeoff.png.
# Each (subject, variant) is trained and evaluated by the same rules as the main run
# (`use rule ... with:`), under results/{dataset}/{subject}/tradeoff/{variant}/.


use rule train as tradeoff_train with:
    output:
        model=PATHS["variant_model"],
        losses=PATHS["variant_losses"],
    params:
        out=lambda w: PATHS["variant_stage_dir"].format(**w),
        preset=lambda w: stage_training(w)[0],
        settings=lambda w: stage_training(w)[1],
        device=config["device"],
        perceptual=lambda w: str(Path(PATHS["perceptual_vgg"]).parent),
    log:
        log_path("tradeoff_train", "{dataset}_{subject}_{variant}_stage{stage}"),
    benchmark:
        benchmark_path("tradeoff_train", "{dataset}_{subject}_{variant}_stage{stage}")


use rule evaluate as tradeoff_evaluate with:
    input:
        unpack(variant_eval_inputs),
    params:
        args=variant_eval_args,
        perceptual=lambda w, input: str(Path(input.alex).parent),
        device=config["device"],
    output:
        metrics=PATHS["variant_metrics"],
        summary=PATHS["variant_summary"],
    log:
        log_path("tradeoff_evaluate", "{dataset}_{subject}_{variant}"),
    benchmark:
        benchmark_path("tradeoff_evaluate", "{dataset}_{subject}_{variant}")


rule matmul_peak:
    output:
        PATHS["matmul_peak"],
    params:
        device=config["device"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("matmul_peak"),
    threads: 2
    shell:
        "delta matmul-peak --out {output:q} --threads {threads} --device {params.device:q} > {log:q} 2>&1"


rule profile_step:
    input:
        model=variant_model,
        record=PATHS["record"],
        body=body_model_file(),
    output:
        PATHS["variant_profile"],
    params:
        steps=TRADE["profile_steps"],
        device=config["device"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("profile_step", "{dataset}_{subject}_{variant}"),
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
    shell:
        "delta profile-step --model {input.model:q} --record {input.record:q} --body {input.body:q} --out {output:q}"
        " --steps {params.steps:q} --device {params.device:q} --threads {threads} > {log:q} 2>&1"


rule tradeoff_table:
    input:
        tradeoff_inputs,
    output:
        csv=PATHS["tradeoff_csv"],
        png=report(
            PATHS["tradeoff_png"],
            caption="../workflow/report/tradeoff.rst",
            category="Trade-off",
            labels={"dataset": "{dataset}", "figure": "trade-off"},
        ),
    params:
        manifest=lambda w: json.dumps(tradeoff_manifest(w)),
        peak=PATHS["matmul_peak"],
        reference=TRADE["reference"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("tradeoff_table", "{dataset}"),
    shell:
        "delta tradeoff --manifest {params.manifest:q} --peak {params.peak:q} --reference {params.reference:q}"
        " --out {output.csv:q} --plot {output.png:q} > {log:q} 2>&1"
