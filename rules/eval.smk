# Evaluation, export and the per-dataset table: results/{dataset}/metrics.csv.
# Which stage is scored and exported: evaluation.stage (2 by default).

EVAL = config["evaluation"]
EXPORT = config["export"]


def configured(wildcards):
    """Fail at DAG construction, naming what is configured, when a target names anything else."""
    if wildcards.dataset not in DATASETS:
        raise ValueError(f"dataset '{wildcards.dataset}' is not configured; configured datasets: {sorted(DATASETS)}")
    subjects = DATASETS[wildcards.dataset]["subjects"]
    if "subject" in wildcards.keys() and wildcards.subject not in subjects:
        raise ValueError(f"subject '{wildcards.subject}' is not configured for dataset '{wildcards.dataset}'; "
                         f"configured subjects: {sorted(subjects)}")  # fmt: skip
    return []


def evaluated_model(wildcards):
    configured(wildcards)
    return PATHS["stage_model"].format(stage=EVAL["stage"], **wildcards)


def eval_inputs(wildcards):
    configured(wildcards)
    files = {
        "model": evaluated_model(wildcards),
        "record": PATHS["record"].format(**wildcards),
        "body": body_model_file(),
        "alex": PATHS["perceptual_alex"],
    }
    if dataset_kind(wildcards.dataset) == "synthetic":  # ground truth for the geometry columns
        files["gt"] = PATHS["syn_meshes"].format(subject=wildcards.subject)
        files["export"] = PATHS["export_json"].format(**wildcards)
    return files


def eval_args(wildcards, input):
    args = f"--max-frames {EVAL['max_frames']} --refine-steps {EVAL['refine_steps']} --splits {' '.join(EVAL['splits'])}"
    if not EVAL["report_unrefined"]:
        args += " --refined-only"
    if EVAL["lpips_alex"]:
        args += " --lpips-alex " + " ".join(f"'{p}'" for p in EVAL["lpips_alex"])
    if "gt" in input.keys():
        args += f" --gt-meshes {input.gt}"
    if "export" in input.keys():
        args += f" --export-dir {Path(input.export).parent}"
    return args


def export_args(wildcards):
    e = EXPORT
    return (f"--grid {e['grid']} --threshold {e['threshold']} --smooth {e['smooth']} --decimate {e['decimate']}"
            f" --min-component-faces {e['min_component_faces']} --turntable-frames {e['turntable_frames']}"
            f" --fps {e['fps']} --sidebyside {e['sidebyside']}")  # fmt: skip


def dataset_subjects(wildcards):
    configured(wildcards)
    return list(DATASETS[wildcards.dataset]["subjects"])


def aggregate_inputs(wildcards):
    subjects = dataset_subjects(wildcards)
    fmt = lambda key, **kw: [PATHS[key].format(dataset=wildcards.dataset, subject=s, **kw) for s in subjects]  # noqa: E731
    return {
        "summaries": fmt("eval_summary"),
        "exports": fmt("export_json"),
        "plots": fmt("loss_plot", stage=1) + fmt("loss_plot", stage=2),
        "bench1": [benchmark_path("train_stage1", f"{wildcards.dataset}_{s}") for s in subjects],
        "bench2": [benchmark_path("train_stage2", f"{wildcards.dataset}_{s}") for s in subjects],
    }


def aggregate_benchmarks(wildcards, input):
    subjects = dataset_subjects(wildcards)
    pairs = [f"{s}/stage1={b}" for s, b in zip(subjects, input.bench1)]
    pairs += [f"{s}/stage2={b}" for s, b in zip(subjects, input.bench2)]
    return " ".join(pairs)


def dataset_metrics_targets():
    return [PATHS["dataset_metrics"].format(dataset=d) for d in DATASETS]


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
    shell:
        "delta plot-losses --losses {input} --out {output} --title '{wildcards.subject}, stage {wildcards.stage}' > {log} 2>&1"


rule export_avatar:
    input:
        model=evaluated_model,
        record=PATHS["record"],
        body=body_model_file(),
    output:
        json=PATHS["export_json"],
        glb=PATHS["export_glb"],
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
    params:
        out=lambda w: PATHS["export_dir"].format(**w),
        args=export_args,
        device=config["device"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("export_avatar", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("export_avatar", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=lambda w, attempt: 20 * attempt,
    shell:
        "delta export --model {input.model} --record {input.record} --body {input.body} --out {params.out}"
        " {params.args} --device {params.device} --threads {threads} > {log} 2>&1"


rule evaluate:
    input:
        unpack(eval_inputs),
    output:
        metrics=PATHS["eval_metrics"],
        summary=PATHS["eval_summary"],
    params:
        args=eval_args,
        perceptual=lambda w, input: str(Path(input.alex).parent),
        device=config["device"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("evaluate", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("evaluate", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(2500, attempt),
        runtime=lambda w, attempt: 30 * attempt,
    shell:
        "delta evaluate --model {input.model} --record {input.record} --body {input.body} --subject {wildcards.subject}"
        " --out {output.metrics} --summary {output.summary} --perceptual {params.perceptual} {params.args}"
        " --device {params.device} --threads {threads} > {log} 2>&1"


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
    params:
        subjects=dataset_subjects,
        benchmarks=aggregate_benchmarks,
    log:
        log_path("aggregate_metrics", "{dataset}"),
    shell:
        "delta aggregate --dataset {wildcards.dataset} --subjects {params.subjects} --summaries {input.summaries}"
        " --exports {input.exports} --benchmarks {params.benchmarks} --out {output} > {log} 2>&1"
