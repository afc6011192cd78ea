# Body-model initialisation: shared shape, per-frame pose and camera fitted to the keypoints.


rule fit_init:
    input:
        record=PATHS["record"],
        body=body_model_file,
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


rule analyze_scene:
    input:
        record=PATHS["record"],
        init=PATHS["init_params"],
        body=body_model_file,
    output:
        report(
            PATHS["scene"],
            caption="../workflow/report/scene.rst",
            category="Scene",
            labels={"subject": "{subject}", "dataset": "{dataset}"},
        ),
    log:
        log_path("analyze_scene", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("analyze_scene", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=3000,
        runtime=30,
    params:
        settings=scene_settings_json,
    shell:
        "delta analyze-scene --record {input.record:q} --init {input.init:q} --body {input.body:q}"
        " --settings {params.settings:q} --out {output:q} --threads {threads} > {log:q} 2>&1"
