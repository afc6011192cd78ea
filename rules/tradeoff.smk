# The speed/accuracy sweep: results/{dataset}/tradeoff.csv and tradeoff.png.
# Each (subject, variant) is trained and evaluated by the same rules as the main run
# (`use rule ... with:`), under results/{dataset}/{subject}/tradeoff/{variant}/.

TRADE = config["tradeoff"]
VARIANT_DIR = "results/{dataset}/{subject}/tradeoff/{variant}"
PATHS |= {
    "variant_stage_dir": VARIANT_DIR + "/stage{stage}",
    "variant_model": VARIANT_DIR + "/stage{stage}/model.pt",
    "variant_losses": VARIANT_DIR + "/stage{stage}/losses.csv",
    "variant_metrics": VARIANT_DIR + "/eval/metrics.csv",
    "variant_summary": VARIANT_DIR + "/eval/summary.json",
    "variant_profile": VARIANT_DIR + "/profile.json",
    "matmul_peak": "results/benchmarks/matmul_peak.json",
    "tradeoff_csv": "results/{dataset}/tradeoff.csv",
    "tradeoff_png": "results/{dataset}/tradeoff.png",
}


wildcard_constraints:
    variant="[A-Za-z0-9_.-]+",


def variant_spec(variant):
    if variant not in TRADE["variants"]:
        raise ValueError(f"trade-off variant '{variant}' is not configured; configured: {sorted(TRADE['variants'])}")
    spec = dict(TRADE["variants"][variant])
    return spec.pop("preset", None), int(spec.pop("stages", 2)), spec


def variant_training(subject, variant):
    """(preset, overrides): the subject's training settings with the variant's on top."""
    preset, overrides = subject_training(subject)
    own_preset, _, over = variant_spec(variant)
    return own_preset or preset, overrides + [over]


def tradeoff_subjects(dataset):
    return TRADE["subjects"] or list(DATASETS[dataset]["subjects"])


# every swept variant's settings are checked now, before any job runs
for _d in DATASETS:
    for _s in tradeoff_subjects(_d):
        for _v in TRADE["variants"]:
            resolve_training(*[variant_training(_s, _v)[0]] + variant_training(_s, _v)[1])


def variant_stages(variant):
    return variant_spec(variant)[1]


def variant_model(wildcards):
    """The model a variant is scored with: its last stage."""
    return PATHS["variant_model"].format(stage=variant_stages(wildcards.variant), **wildcards)


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


def variant_stage2_inputs(wildcards):
    files = {"stage1": PATHS["variant_model"].format(stage=1, **wildcards)}
    preset, overrides = variant_training(wildcards.subject, wildcards.variant)
    st = resolve_training(preset, *overrides)
    if st.semantic != "none" and st.weights.semantic > 0:
        files["vgg"] = PATHS["perceptual_vgg"]
    return files


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


def variant_eval_inputs(wildcards):
    configured(wildcards)
    files = {
        "model": variant_model(wildcards),
        "record": PATHS["record"].format(**wildcards),
        "body": body_model_file(),
        "alex": PATHS["perceptual_alex"],
    }
    if dataset_kind(wildcards.dataset) == "synthetic":
        files["gt"] = PATHS["syn_meshes"].format(subject=wildcards.subject)
    return files


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


rule matmul_peak:
    output:
        PATHS["matmul_peak"],
    log:
        log_path("matmul_peak"),
    threads: 2
    shell:
        "delta matmul-peak --out {output} --threads {threads} --device {config[device]} > {log} 2>&1"


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
    log:
        log_path("profile_step", "{dataset}_{subject}_{variant}"),
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
    shell:
        "delta profile-step --model {input.model} --record {input.record} --body {input.body} --out {output}"
        " --steps {params.steps} --device {params.device} --threads {threads} > {log} 2>&1"


def tradeoff_manifest(wildcards):
    """{subject: {variant: {role: path}}} of every swept (subject, variant)."""
    configured(wildcards)
    out = {}
    for s in tradeoff_subjects(wildcards.dataset):
        for v in TRADE["variants"]:
            w = {"dataset": wildcards.dataset, "subject": s, "variant": v}
            last = variant_stages(v)
            files = {
                "summary": PATHS["variant_summary"].format(**w),
                "profile": PATHS["variant_profile"].format(**w),
            }
            for k in range(1, last + 1):
                files[f"losses{k}"] = PATHS["variant_losses"].format(stage=k, **w)
                files[f"bench{k}"] = benchmark_path(f"tradeoff_stage{k}", f"{wildcards.dataset}_{s}_{v}")
            out.setdefault(s, {})[v] = files
    return out


def tradeoff_inputs(wildcards):
    files = [p for variants in tradeoff_manifest(wildcards).values() for f in variants.values() for p in f.values()]
    return files + [PATHS["matmul_peak"]]


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
    log:
        log_path("tradeoff_table", "{dataset}"),
    shell:
        "delta tradeoff --manifest {params.manifest:q} --peak {params.peak} --reference {params.reference}"
        " --out {output.csv} --plot {output.png} > {log} 2>&1"
