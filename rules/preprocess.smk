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
        video=video_input,
        model=matting_model(),
    output:
        PATHS["matting"],
    params:
        model=PRE["matting"]["model"],
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
        "delta matte --video {input.video} --model {params.model} --path {input.model} --out {output}"
        " --threads {threads} > {log} 2>&1"


rule parse:
    input:
        video=video_input,
        model=parsing_model(),
    output:
        PATHS["parsing"],
    params:
        model=PRE["parsing"]["model"],
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
        "delta parse --video {input.video} --model {params.model} --path {input.model} --out {output}"
        " --threads {threads} > {log} 2>&1"


rule keypoints:
    input:
        video=video_input,
        model=PATHS["mediapipe_pose"],
        face=PATHS["mediapipe_face"] if PRE["face_landmarks"] else [],
    output:
        PATHS["keypoints"],
    params:
        model=PRE["keypoints"]["model"],
        face=lambda w, input: f"--face-path {input.face}" if PRE["face_landmarks"] else "",
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("keypoints", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("keypoints", "{dataset}_{subject}")
    resources:
        mem_mb=2000,
    shell:
        "delta keypoints --video {input.video} --model {params.model} --path {input.model} {params.face}"
        " --out {output} > {log} 2>&1"


rule convert_mediapipe:
    output:
        pose=PATHS["mediapipe_pose"],
        face=PATHS["mediapipe_face"],
    params:
        out=lambda w: str(Path(PATHS["mediapipe_pose"]).parent),
        env=f"{PRE['envs_dir']}/mediapipe-convert",
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("convert_mediapipe"),
    benchmark:
        benchmark_path("convert_mediapipe")
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "delta convert-mediapipe --out {params.out} --env {params.env} > {log} 2>&1"
