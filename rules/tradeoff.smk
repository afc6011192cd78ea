# The speed/accuracy sweep, an opt-in study: included when the config has a 'tradeoff' section
# (config/tradeoff.yaml): snakemake --cores 2 results/synthetic/tradeoff.csv --configfile config/tradeoff.yaml
# Each (subject, variant) is trained and evaluated by the same rules as the main run
# (`use rule ... with:`), under results/{dataset}/{subject}/tradeoff/{variant}/.

TRADE = config["tradeoff"]


localrules:
    tradeoff_table,


PATHS |= {
    "variant_stage_dir": "results/{dataset}/{subject}/tradeoff/{variant}/stage{stage}",
    "variant_model": "results/{dataset}/{subject}/tradeoff/{variant}/stage{stage}/model.pt",
    "variant_losses": "results/{dataset}/{subject}/tradeoff/{variant}/stage{stage}/losses.csv",
    "variant_metrics": "results/{dataset}/{subject}/tradeoff/{variant}/eval/metrics.csv",
    "variant_summary": "results/{dataset}/{subject}/tradeoff/{variant}/eval/summary.json",
    "variant_profile": "results/{dataset}/{subject}/tradeoff/{variant}/profile.json",
    "matmul_peak": "results/benchmarks/matmul_peak.json",
    "tradeoff_csv": "results/{dataset}/tradeoff.csv",
    "tradeoff_png": "results/{dataset}/tradeoff.png",
}


def variant_spec(variant):
    if variant not in TRADE["variants"]:
        raise ValueError(
            f"trade-off variant '{variant}' is not configured; configured: {sorted(TRADE['variants'])}"
        )
    spec = dict(TRADE["variants"][variant])
    spec.pop("subjects", None)
    spec.pop("inherit_training", None)
    return spec.pop("preset", None), int(spec.pop("stages", 2)), spec


def variant_subjects(dataset, variant):
    """The swept subjects a variant runs on (its own 'subjects' list narrows the sweep's)."""
    own = TRADE["variants"][variant].get("subjects") or []
    return [s for s in tradeoff_subjects(dataset) if not own or s in own]


def variant_training(subject, variant):
    """(preset, overrides) of a sweep variant on a subject."""
    variant_spec(variant)
    return _variant_training(config, subject, variant)


def tradeoff_subjects(dataset):
    return TRADE["subjects"] or list(DATASETS[dataset]["subjects"])


def variant_stages(variant):
    return variant_spec(variant)[1]


def variant_is_main(subject, variant):
    """True when a variant trains exactly what the main run trains: its stages are the main run's (the
    same settings, and the same of them set by the config over the scene analysis: a variant that sets
    the preset's own resolution keeps it, where the main run takes the scene's)."""
    preset, overrides = variant_training(subject, variant)
    main, main_overrides = subject_training(subject)
    return (
        preset == main
        and resolve_training(preset, *overrides).raw == TRAINING[subject].raw
        and user_decided(set_keys(overrides)) == user_decided(set_keys(main_overrides))
    )


def variant_stage_file(kind, stage, **w):
    """A variant's stage output (``model``, ``losses`` or ``bench``): the main run's when it is the main run."""
    if variant_is_main(w["subject"], w["variant"]):
        if kind == "bench":
            return benchmark_path(
                "train", f"{w['dataset']}_{w['subject']}_stage{stage}"
            )
        return PATHS[f"stage_{kind}"].format(stage=stage, **w)
    if kind == "bench":
        return benchmark_path(
            "tradeoff_train",
            f"{w['dataset']}_{w['subject']}_{w['variant']}_stage{stage}",
        )
    return PATHS[f"variant_{kind}"].format(stage=stage, **w)


def variant_model(wildcards):
    """The model a variant is scored with: its last stage."""
    return variant_stage_file("model", variant_stages(wildcards.variant), **wildcards)


def variant_eval_inputs(wildcards):
    configured(wildcards)
    files = {
        "model": variant_model(wildcards),
        "record": PATHS["record"].format(**wildcards),
        "body": body_model_file(wildcards),
        "alex": PATHS["perceptual_alex"],
    }
    if dataset_kind(wildcards.dataset) == "synthetic":
        files["gt"] = PATHS["syn_meshes"].format(subject=wildcards.subject)
    return files


def tradeoff_manifest(wildcards):
    """{subject: {variant: {role: path}}} of every swept (subject, variant)."""
    configured(wildcards)
    out = {}
    for s in tradeoff_subjects(wildcards.dataset):
        for v in TRADE["only"] or TRADE["variants"]:
            if s not in variant_subjects(wildcards.dataset, v):
                continue
            w = {"dataset": wildcards.dataset, "subject": s, "variant": v}
            last = variant_stages(v)
            files = {
                "summary": PATHS["variant_summary"].format(**w),
                "profile": PATHS["variant_profile"].format(**w),
            }
            for k in range(1, last + 1):
                files[f"losses{k}"] = variant_stage_file("losses", k, **w)
                files[f"bench{k}"] = variant_stage_file("bench", k, **w)
            out.setdefault(s, {})[v] = files
    return out


def variant_eval_settings(wildcards):
    """The evaluation section with the study's own frames, refinement and splits."""
    return eval_settings(wildcards, {**EVAL, **TRADE["evaluation"]})


def tradeoff_inputs(wildcards):
    files = [
        p
        for variants in tradeoff_manifest(wildcards).values()
        for f in variants.values()
        for p in f.values()
    ]
    return files + [PATHS["matmul_peak"]]


use rule train as tradeoff_train with:
    output:
        model=PATHS["variant_model"],
        losses=PATHS["variant_losses"],
    log:
        log_path("tradeoff_train", "{dataset}_{subject}_{variant}_stage{stage}"),
    benchmark:
        benchmark_path("tradeoff_train", "{dataset}_{subject}_{variant}_stage{stage}")
    params:
        out=lambda w: PATHS["variant_stage_dir"].format(**w),
        settings=stage_training,
        device=config["device"],
        perceptual=lambda w: str(Path(PATHS["perceptual_vgg"]).parent),


use rule evaluate as tradeoff_evaluate with:
    input:
        unpack(variant_eval_inputs),
    output:
        metrics=PATHS["variant_metrics"],
        summary=PATHS["variant_summary"],
    log:
        log_path("tradeoff_evaluate", "{dataset}_{subject}_{variant}"),
    benchmark:
        benchmark_path("tradeoff_evaluate", "{dataset}_{subject}_{variant}")
    params:
        settings=variant_eval_settings,
        truth=eval_truth,
        perceptual=lambda w, input: str(Path(input.alex).parent),
        device=config["device"],


rule matmul_peak:
    output:
        PATHS["matmul_peak"],
    log:
        log_path("matmul_peak"),
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    params:
        device=config["device"],
    shell:
        "delta matmul-peak --out {output:q} --threads {threads} --device {params.device:q} > {log:q} 2>&1"


rule profile_step:
    input:
        model=variant_model,
        record=PATHS["record"],
        body=body_model_file,
    output:
        PATHS["variant_profile"],
    log:
        log_path("profile_step", "{dataset}_{subject}_{variant}"),
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
    params:
        steps=TRADE["profile_steps"],
        device=config["device"],
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
    log:
        log_path("tradeoff_table", "{dataset}"),
    conda:
        "../workflow/envs/delta.yaml"
    params:
        manifest=lambda w: json.dumps(tradeoff_manifest(w)),
        peak=PATHS["matmul_peak"],
        reference=TRADE["reference"],
    shell:
        "delta tradeoff --manifest {params.manifest:q} --peak {params.peak:q} --reference {params.reference:q}"
        " --out {output.csv:q} --plot {output.png:q} > {log:q} 2>&1"
