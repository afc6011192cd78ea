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
        size=PRE["resolution"],
        margin=PRE["crop_margin"],
        use=lambda w: " ".join(used_provided(w.dataset)),
        steps=lambda w: " ".join(step_files(w).values()),
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("prepare_frames", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("prepare_frames", "{dataset}_{subject}")
    resources:
        mem_mb=prepare_mem_mb,
        runtime=30,
    shell:
        "delta prepare --kind {params.kind} --root {params.root} --subject {wildcards.subject}"
        " --subject-config {params.cfg:q} --size {params.size} --margin {params.margin}"
        " --use-provided {params.use} --steps {params.steps}"
        " --out {output.record} --summary {output.summary} > {log} 2>&1"


rule matte:
    input:
        video_input,
    output:
        PATHS["matting"],
    params:
        model=PRE["matting"]["model"],
        path=PRE["matting"]["path"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("matte", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("matte", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=4000,
    shell:
        "delta matte --video {input} --model {params.model} --path {params.path} --out {output}"
        " --threads {threads} > {log} 2>&1"


rule parse:
    input:
        video_input,
    output:
        PATHS["parsing"],
    params:
        model=PRE["parsing"]["model"],
        path=PRE["parsing"]["path"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("parse", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("parse", "{dataset}_{subject}")
    threads: 2
    resources:
        mem_mb=4000,
    shell:
        "delta parse --video {input} --model {params.model} --path {params.path} --out {output}"
        " --threads {threads} > {log} 2>&1"
