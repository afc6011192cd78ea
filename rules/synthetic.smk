# Embedded default: synthetic monocular captures with ground truth, generated on the Anny model.


rule synthesize:
    input:
        body=anny_model_file(),
        shape_space=PATHS["anny_shape_space"],
        expressions=synthetic_expressions,
    output:
        video=PATHS["syn_video"],
        params=PATHS["syn_params"],
        frames=PATHS["syn_frames"],
        meshes=PATHS["syn_meshes"],
        splits=PATHS["syn_splits"],
    log:
        log_path("synthesize", "{subject}"),
    benchmark:
        benchmark_path("synthesize", "{subject}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=synth_mem_mb,
        runtime=synth_runtime,
    params:
        spec=synthetic_spec_json,
        expressions=lambda w, input: (
            ["--expressions", input.expressions] if input.expressions else []
        ),
        cache=PATHS["anny_cache"],
        out=lambda w: str(Path(PATHS["syn_video"].format(subject=w.subject)).parent),
    shell:
        "delta synthesize --subject {wildcards.subject:q} --settings {params.spec:q} --body {input.body:q}"
        " --shape-space {input.shape_space:q} --anny-cache {params.cache:q} --out {params.out:q}"
        " {params.expressions:q} --threads {threads} > {log:q} 2>&1"


rule synthetic_peoplesnapshot:
    input:
        video=PATHS["syn_video"],
        params=PATHS["syn_params"],
        frames=PATHS["syn_frames"],
    output:
        peoplesnapshot_files("{subject}"),
    log:
        log_path("synthetic_peoplesnapshot", "{subject}"),
    conda:
        "../workflow/envs/delta.yaml"
    resources:
        mem_mb=2000,
    params:
        capture=lambda w: str(Path(PATHS["syn_video"].format(subject=w.subject)).parent),
        out=lambda w: PATHS["syn_ps_dir"].format(subject=w.subject),
    shell:
        "delta to-peoplesnapshot --capture {params.capture:q} --subject {wildcards.subject:q}"
        " --out {params.out:q} > {log:q} 2>&1"
