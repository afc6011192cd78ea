# Preprocessing: the common per-frame record training reads, from whatever the dataset provides.


rule prepare_frames:
    input:
        unpack(prepare_inputs),
    output:
        record=PATHS["record"],
        summary=PATHS["record_summary"],
    params:
        kind=lambda w: dataset_kind(w.dataset),
        root=prepare_root,
        cfg=subject_config_json,
        size=config["preprocess"]["resolution"],
        margin=config["preprocess"]["crop_margin"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("prepare_frames", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("prepare_frames", "{dataset}_{subject}")
    resources:
        mem_mb=3000,
    shell:
        "delta prepare --kind {params.kind} --root {params.root} --subject {wildcards.subject}"
        " --subject-config {params.cfg:q} --size {params.size} --margin {params.margin}"
        " --out {output.record} --summary {output.summary} > {log} 2>&1"
