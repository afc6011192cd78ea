# Body-model initialisation: shared shape, per-frame pose and camera fitted to the keypoints.


rule fit_init:
    input:
        record=PATHS["record"],
        body=body_model_file(),
    output:
        params=PATHS["init_params"],
        report=PATHS["init_report"],
    log:
        log_path("fit_init", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("fit_init", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=3000,
        runtime=60,
    params:
        out=lambda w: str(Path(PATHS["init_params"].format(**w)).parent),
        settings=fit_settings_json,
    shell:
        "delta fit-init --record {input.record:q} --body {input.body:q} --out {params.out:q}"
        " --settings {params.settings:q} --threads {threads} > {log:q} 2>&1"
