# The speed/accuracy sweep: results/{dataset}/tradeoff.csv and tradeoff.png.
# Each (subject, variant) is trained and evaluated by the same rules as the main run
# (`use rule ... with:`), under results/{dataset}/{subject}/tradeoff/{variant}/.


use rule train_stage1 as tradeoff_stage1 with:
    output:
        model=PATHS["variant_model"].replace("{stage}", "1"),
        losses=PATHS["variant_losses"].replace("{stage}", "1"),
    params:
        out=lambda w: PATHS["variant_stage_dir"].format(stage=1, **w),
        preset=lambda w: variant_training(w.subject, w.variant)[0],
        overrides=lambda w: json.dumps(variant_training(w.subject, w.variant)[1], sort_keys=True),
        device=config["device"],
    log:
        log_path("tradeoff_stage1", "{dataset}_{subject}_{variant}"),
    benchmark:
        benchmark_path("tradeoff_stage1", "{dataset}_{subject}_{variant}")


use rule train_stage2 as tradeoff_stage2 with:
    input:
        unpack(variant_stage2_inputs),
        record=PATHS["record"],
        body=body_model_file(),
    output:
        model=PATHS["variant_model"].replace("{stage}", "2"),
        losses=PATHS["variant_losses"].replace("{stage}", "2"),
    params:
        out=lambda w: PATHS["variant_stage_dir"].format(stage=2, **w),
        preset=lambda w: variant_training(w.subject, w.variant)[0],
        overrides=lambda w: json.dumps(variant_training(w.subject, w.variant)[1], sort_keys=True),
        device=config["device"],
        perceptual=lambda w: str(Path(PATHS["perceptual_vgg"]).parent),
    log:
        log_path("tradeoff_stage2", "{dataset}_{subject}_{variant}"),
    benchmark:
        benchmark_path("tradeoff_stage2", "{dataset}_{subject}_{variant}")


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
        "delta matmul-peak --out {output} --threads {threads} --device {params.device} > {log} 2>&1"


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
        "delta profile-step --model {input.model} --record {input.record} --body {input.body} --out {output}"
        " --steps {params.steps} --device {params.device} --threads {threads} > {log} 2>&1"


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
        "delta tradeoff --manifest {params.manifest:q} --peak {params.peak} --reference {params.reference}"
        " --out {output.csv} --plot {output.png} > {log} 2>&1"
