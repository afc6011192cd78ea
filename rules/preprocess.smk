# Preprocessing: the common per-frame record training reads, from whatever the dataset provides.


rule prepare_frames:
    input:
        unpack(prepare_inputs),
    output:
        record=PATHS["record"],
        summary=PATHS["record_summary"],
    log:
        log_path("prepare_frames", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("prepare_frames", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=prepare_mem_mb,
        runtime=30,
    params:
        root=prepare_root,
        settings=prepare_settings,
        steps=lambda w: list(step_files(w).values()),
        embedding=lambda w: (
            ["--face-embedding", face_embedding(w)] if face_embedding(w) else []
        ),
    shell:
        "delta prepare --root {params.root:q} --subject {wildcards.subject:q} --settings {params.settings:q}"
        " --steps {params.steps:q} {params.embedding:q} --out {output.record:q} --summary {output.summary:q}"
        " > {log:q} 2>&1"


rule matte:
    input:
        video=video_input,
        model=matting_model(),
        head=head_models,
    output:
        PATHS["matting"],
    log:
        log_path("matte", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("matte", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=4000,
    params:
        model=PRE["matting"]["model"],
        select=step_selection,
    shell:
        "delta matte --video {input.video:q} --model {params.model:q} --path {input.model:q} --out {output:q}"
        " {params.select:q} --threads {threads} > {log:q} 2>&1"


rule parse:
    input:
        video=video_input,
        model=parsing_model(),
        head=head_models,
        person=parsed_person,
    output:
        PATHS["parsing"],
    log:
        log_path("parse", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("parse", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=4000,
    params:
        model=PRE["parsing"]["model"],
        select=step_selection,
        person=lambda w, input: ["--person", input.person] if input.person else [],
    shell:
        "delta parse --video {input.video:q} --model {params.model:q} --path {input.model:q} --out {output:q}"
        " {params.select:q} {params.person:q} --threads {threads} > {log:q} 2>&1"


rule keypoints:
    input:
        video=video_input,
        model=PATHS["mediapipe_pose"],
        face=PATHS["mediapipe_face"] if PRE["face_landmarks"] else [],
        head=head_models,
    output:
        PATHS["keypoints"],
    log:
        log_path("keypoints", "{dataset}_{subject}"),
    benchmark:
        benchmark_path("keypoints", "{dataset}_{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=2000,
    params:
        model=PRE["keypoints"]["model"],
        select=step_selection,
        face=lambda w, input: (
            ["--face-path", input.face] if PRE["face_landmarks"] else []
        ),
    shell:
        "delta keypoints --video {input.video:q} --model {params.model:q} --path {input.model:q} {params.face:q}"
        " {params.select:q} --out {output:q} > {log:q} 2>&1"


rule convert_mediapipe:
    output:
        pose=PATHS["mediapipe_pose"],
        face=PATHS["mediapipe_face"],
        detector=PATHS["mediapipe_detector"],
    log:
        log_path("convert_mediapipe"),
    benchmark:
        benchmark_path("convert_mediapipe")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        out=lambda w: str(Path(PATHS["mediapipe_pose"]).parent),
        env=f"{PRE['envs_dir']}/mediapipe-convert",
    shell:
        "delta convert-mediapipe --out {params.out:q} --env {params.env:q} > {log:q} 2>&1"
