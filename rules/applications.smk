# The trained avatars in use (docs/applications.md): driven by another motion.


rule animate:
    input:
        unpack(animate_inputs),
    output:
        video=report(
            PATHS["animation"],
            caption="../workflow/report/animation.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "motion": "{motion}"},
        ),
        summary=PATHS["animation_json"],
        glb=PATHS["animation_glb"],
    log:
        log_path("animate", "{dataset}_{subject}_{motion}"),
    benchmark:
        benchmark_path("animate", "{dataset}_{subject}_{motion}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=application_runtime(at_most(ANIMATE_SETTINGS.max_frames), 30),
    params:
        out=lambda w: PATHS["animate_dir"].format(**w),
        clothing=animate_clothing,
        settings=json.dumps(ANIMATE, sort_keys=True),
        device=config["device"],
    shell:
        "delta animate --model {input.model:q} --record {input.record:q} --body {input.body:q}"
        " --motion {input.motion:q} {params.clothing:q} --out {params.out:q} --settings {params.settings:q}"
        " --device {params.device:q} --threads {threads} > {log:q} 2>&1"


rule dress:
    input:
        unpack(dress_inputs),
    output:
        dressed=report(
            PATHS["dressed"],
            caption="../workflow/report/dressed.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "wears": "{exterior}", "view": "frame"},
        ),
        turntable=report(
            PATHS["dressed_turntable"],
            caption="../workflow/report/dressed.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={
                "subject": "{subject}",
                "wears": "{exterior}",
                "view": "turntable",
            },
        ),
        summary=PATHS["dress_json"],
        scores=PATHS["dress_scores"],
    log:
        log_path("dress", "{dataset}_{subject}_{exterior}"),
    benchmark:
        benchmark_path("dress", "{dataset}_{subject}_{exterior}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(4000, attempt),
        runtime=application_runtime(
            shown(DRESS_SETTINGS), 20, scored=show_scored(DRESS_SETTINGS)
        ),
    params:
        out=lambda w: PATHS["dress_dir"].format(**w),
        truth=truth_args,
        layers=layer_args,
        settings=json.dumps(DRESS, sort_keys=True),
        device=config["device"],
    shell:
        "delta dress --model {input.model:q} --record {input.record:q} --wearer-model {input.wearer_model:q}"
        " --wearer-record {input.wearer_record:q} --body {input.body:q} --wearer-body {input.wearer_body:q}"
        " --out {params.out:q} {params.truth:q} {params.layers:q}"
        " --settings {params.settings:q} --device {params.device:q} --threads {threads} > {log:q} 2>&1"


rule reshape:
    input:
        unpack(reshape_inputs),
    output:
        reshaped=report(
            PATHS["reshaped"],
            caption="../workflow/report/reshaped.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "shape": "{shape}", "view": "frame"},
        ),
        turntable=report(
            PATHS["reshaped_turntable"],
            caption="../workflow/report/reshaped.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "shape": "{shape}", "view": "turntable"},
        ),
        summary=PATHS["reshape_json"],
        scores=PATHS["reshape_scores"],
    log:
        log_path("reshape", "{dataset}_{subject}_{shape}"),
    benchmark:
        benchmark_path("reshape", "{dataset}_{subject}_{shape}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(4000, attempt),
        runtime=application_runtime(
            shown(RESHAPE_SETTINGS), 20, scored=show_scored(RESHAPE_SETTINGS)
        ),
    params:
        out=lambda w: PATHS["reshape_dir"].format(**w),
        edit=reshape_args,
        truth=truth_args,
        settings=json.dumps(RESHAPE, sort_keys=True),
        device=config["device"],
    shell:
        "delta reshape --model {input.model:q} --record {input.record:q} --body {input.body:q} {params.edit:q}"
        " {params.truth:q} --out {params.out:q} --settings {params.settings:q} --device {params.device:q} --threads {threads}"
        " > {log:q} 2>&1"


rule application_scores:
    input:
        application_score_inputs,
    output:
        report(
            PATHS["application_scores"],
            caption="../workflow/report/applications.rst",
            category="Metrics",
            labels={"dataset": "{dataset}", "table": "applications"},
        ),
    log:
        log_path("application_scores", "{dataset}"),
    conda:
        "../workflow/envs/delta.yaml"
    shell:
        "delta application-scores --scores {input:q} --out {output:q} > {log:q} 2>&1"


rule tryon:
    input:
        unpack(tryon_inputs),
    output:
        tryon=report(
            PATHS["tryon"],
            caption="../workflow/report/tryon.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "tries on": "{exterior}", "view": "frame"},
        ),
        turntable=PATHS["tryon_turntable"],
        summary=PATHS["tryon_json"],
    log:
        log_path("tryon", "{dataset}_{subject}_{exterior}"),
    benchmark:
        benchmark_path("tryon", "{dataset}_{subject}_{exterior}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=application_runtime(shown(TRYON_SETTINGS), 15, model="wearer_model"),
    params:
        out=lambda w: PATHS["tryon_dir"].format(**w),
        frame=TRYON["frame"],
        layers=layer_args,
        settings=json.dumps(TRYON["settings"], sort_keys=True),
        device=config["device"],
    shell:
        "delta try-on --record {input.record:q} --init {input.init:q} --body {input.body:q} --frame {params.frame}"
        " --wearer-model {input.wearer_model:q} --wearer-record {input.wearer_record:q}"
        " --wearer-body {input.wearer_body:q} --out {params.out:q} {params.layers:q}"
        " --settings {params.settings:q} --device {params.device:q} --threads {threads} > {log:q} 2>&1"


rule reenact:
    input:
        unpack(reenact_inputs),
    output:
        video=report(
            PATHS["reenactment"],
            caption="../workflow/report/reenactment.rst",
            category="Applications",
            subcategory="{dataset} {subject}",
            labels={"subject": "{subject}", "driven by": "{driver}"},
        ),
        summary=PATHS["reenact_json"],
        scores=PATHS["reenact_scores"],
    log:
        log_path("reenact", "{dataset}_{subject}_{driver}"),
    benchmark:
        benchmark_path("reenact", "{dataset}_{subject}_{driver}")
    conda:
        "../workflow/envs/delta.yaml"
    threads: 2
    resources:
        mem_mb=lambda w, attempt: _grow(3000, attempt),
        runtime=application_runtime(
            at_most(REENACT["max_frames"]), 30, scored=reenact_scored
        ),
    params:
        out=lambda w: PATHS["reenact_dir"].format(**w),
        max_frames=REENACT["max_frames"],
        fps=REENACT["fps"],
        truth=reenact_truth_args,
        device=config["device"],
    shell:
        "delta reenact --model {input.model:q} --record {input.record:q} --body {input.body:q}"
        " --driver-model {input.driver_model:q} --driver-record {input.driver_record:q}"
        " --max-frames {params.max_frames} --fps {params.fps} --out {params.out:q} {params.truth:q}"
        " --device {params.device:q} --threads {threads} > {log:q} 2>&1"
