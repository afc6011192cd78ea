# Body-model layer: the shipped Anny model converted once, or the user's SMPL-X, then upsampled.


rule convert_anny:
    output:
        model=PATHS["body_base"].format(model="anny"),
        report=PATHS["body_base_report"].format(model="anny"),
        shape_space=PATHS["anny_shape_space"],
    log:
        log_path("convert_anny"),
    benchmark:
        benchmark_path("convert_anny")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: 6000 * attempt,
        runtime=30,
    params:
        num_shape=BODY["anny"]["num_shape"],
        num_samples=BODY["anny"]["num_samples"],
        seed=BODY["anny"]["seed"],
        merge=BODY["anny"]["merge_bones"],
        cache=PATHS["anny_cache"],
    shell:
        "delta convert-anny --out {output.model:q} --report {output.report:q} --shape-space {output.shape_space:q}"
        " --num-shape {params.num_shape:q} --num-samples {params.num_samples:q} --seed {params.seed:q}"
        " --merge {params.merge:q} --cache-dir {params.cache:q} --threads {threads} > {log:q} 2>&1"


rule anny_expressions:
    output:
        PATHS["anny_expressions"],
    log:
        log_path("anny_expressions"),
    benchmark:
        benchmark_path("anny_expressions")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        cache=PATHS["anny_cache"],
    shell:
        "delta anny-expressions --out {output:q} --cache-dir {params.cache:q} > {log:q} 2>&1"


rule face_body_model:
    input:
        body=PATHS["body"],
        expressions=PATHS["anny_expressions"],
    output:
        PATHS["face_body"],
    log:
        log_path("face_body_model", "{model}_sub{level}"),
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=4000,
    shell:
        "delta attach-expressions --body {input.body:q} --expressions {input.expressions:q} --out {output:q}"
        " > {log:q} 2>&1"


rule face_landmark_embedding:
    input:
        body=embedding_body,
        detector=PATHS["mediapipe_detector"],
        landmarks=PATHS["mediapipe_face"],
    output:
        PATHS["face_embedding"],
    log:
        log_path("face_landmark_embedding", "{model}_sub{level}"),
    benchmark:
        benchmark_path("face_landmark_embedding", "{model}_sub{level}")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    shell:
        "delta embed-face-landmarks --body {input.body:q} --detector {input.detector:q}"
        " --landmarks {input.landmarks:q} --out {output:q} > {log:q} 2>&1"


rule load_smplx:
    input:
        BODY["smplx_path"],
    output:
        PATHS["body_base"].format(model="smplx"),
    log:
        log_path("load_smplx"),
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=2000,
    params:
        num_shape=BODY["smplx"]["num_shape"],
        num_expression=BODY["smplx"]["num_expression"],
    shell:
        "delta load-smplx --src {input:q} --out {output:q}"
        " --num-shape {params.num_shape:q} --num-expression {params.num_expression:q} > {log:q} 2>&1"


rule upsample_body:
    input:
        PATHS["body_base"],
    output:
        model=PATHS["body"],
        summary=PATHS["body_summary"],
    log:
        log_path("upsample_body", "{model}_sub{level}"),
    benchmark:
        benchmark_path("upsample_body", "{model}_sub{level}")
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=4000,
    shell:
        "delta upsample --src {input:q} --out {output.model:q} --level {wildcards.level:q}"
        " --summary {output.summary:q} > {log:q} 2>&1"
