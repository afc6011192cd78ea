# Evaluation, export and the per-dataset table: results/{dataset}/metrics.csv.
# Which stage is scored and exported: evaluation.stage (2 by default).


rule plot_losses:
    input:
        PATHS["stage_losses"],
    output:
        report(
            PATHS["loss_plot"],
            caption="../workflow/report/losses.rst",
            category="Training",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "stage": "{stage}", "figure": "losses"},
        ),
    log:
        log_path("plot_losses", "{dataset}_{subject}_{stage}"),
    conda:
        "../workflow/envs/delta.yaml"
    params:
        title=lambda w: f"{w.subject}, stage {w.stage}",
    shell:
        "delta plot-losses --losses {input:q} --out {output:q} --title {params.title:q} > {log:q} 2>&1"


rule export_meshes:
    input:
        unpack(trained_inputs),
    output:
        json=PATHS["export_meshes"],
        glb=PATHS["export_glb"],
        animated=PATHS["export_animated"],
    log:
        log_path("export_meshes", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("export_meshes", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=lambda w, attempt: 10 * attempt,
    params:
        out=lambda w: PATHS["export_dir"].format(**w),
        settings=export_settings("meshes"),
        device=config["device"],
    shell:
        "delta export --part meshes --model {input.model:q} --record {input.record:q} --body {input.body:q}"
        " --out {params.out:q} --settings {params.settings:q} --device {params.device:q} --threads {threads}"
        " > {log:q} 2>&1"


rule export_avatar:
    input:
        unpack(trained_inputs),
        meshes=PATHS["export_meshes"],
    output:
        json=PATHS["export_json"],
        turntable=report(
            PATHS["turntable"],
            caption="../workflow/report/turntable.rst",
            category="Videos",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "video": "turntable"},
        ),
        novel=report(
            PATHS["novel_pose"],
            caption="../workflow/report/novel_pose.rst",
            category="Videos",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "video": "novel poses"},
        ),
        sidebyside=report(
            directory(PATHS["sidebyside"]),
            patterns=["{name}.png"],
            caption="../workflow/report/sidebyside.rst",
            category="Renders",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "frame": "{name}"},
        ),
    log:
        log_path("export_avatar", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("export_avatar", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=videos_runtime,
    params:
        out=lambda w: PATHS["export_dir"].format(**w),
        settings=export_settings("videos"),
        device=config["device"],
    shell:
        "delta export --part videos --model {input.model:q} --record {input.record:q} --body {input.body:q}"
        " --out {params.out:q} --settings {params.settings:q} --device {params.device:q} --threads {threads}"
        " > {log:q} 2>&1"


rule evaluate:
    input:
        unpack(eval_inputs),
    output:
        metrics=PATHS["eval_metrics"],
        summary=PATHS["eval_summary"],
        worst=report(
            directory(PATHS["eval_worst"]),
            patterns=["{name}.png"],
            caption="../workflow/report/worst.rst",
            category="Renders",
            subcategory="{dataset} {subject}: lowest PSNR",
            labels={"subject": "{subject}", "frame": "{name}"},
        ),
    log:
        log_path("evaluate", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("evaluate", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(2500, attempt),
        runtime=eval_runtime,
    params:
        settings=eval_settings,
        truth=eval_truth,
        perceptual=lambda w, input: str(Path(input.alex).parent),
        device=config["device"],
    shell:
        "delta evaluate --model {input.model:q} --record {input.record:q} --body {input.body:q} --subject {wildcards.subject:q}"
        " --out {output.metrics:q} --summary {output.summary:q} --perceptual {params.perceptual:q}"
        " --settings {params.settings:q} {params.truth:q}"
        " --device {params.device:q} --threads {threads} > {log:q} 2>&1"


rule aggregate_metrics:
    input:
        unpack(aggregate_inputs),
    output:
        report(
            PATHS["dataset_metrics"],
            caption="../workflow/report/metrics.rst",
            category="Metrics",
            labels={"dataset": "{dataset}", "table": "metrics"},
        ),
    log:
        log_path("aggregate_metrics", "{dataset}"),
    conda:
        "../workflow/envs/delta.yaml"
    params:
        subjects=dataset_subjects,
        benchmarks=aggregate_benchmarks,
        source=lambda w: data_source(config, w.dataset),
    shell:
        "delta aggregate --dataset {wildcards.dataset:q} --subjects {params.subjects:q} --summaries {input.summaries:q}"
        " --exports {input.exports:q} --benchmarks {params.benchmarks:q} --source {params.source:q}"
        " --out {output:q} > {log:q} 2>&1"
