# DELTA: disentangled hybrid avatars from monocular video.
# Usage: snakemake --cores 2            (the embedded default)
#        snakemake --cores 2 --configfile .test/config/config.yaml   (tiny CI configuration)
from snakemake.utils import min_version

min_version("8.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "rules/common.smk"
include: "rules/body.smk"
include: "rules/synthetic.smk"
include: "rules/preprocess.smk"
include: "rules/fitting.smk"
include: "rules/training.smk"
include: "rules/eval.smk"
include: "rules/applications.smk"


# the speed/accuracy study, on request: --configfile config/tradeoff.yaml
if "tradeoff" in config:

    include: "rules/tradeoff.smk"


# cheap bookkeeping runs on the submitting machine, never as a cluster job
localrules:
    all,
    synthetic_peoplesnapshot,
    fetch_perceptual,
    plot_losses,
    aggregate_metrics,
    application_scores,


onstart:
    # jobs that run here need the configured device here (a cluster's GPU nodes are checked by their jobs)
    if workflow.local_exec:
        check_device(config["device"])
    for note in config["standin_notes"]:
        logger.warning(note)


rule all:
    default_target: True
    input:
        all_targets(),
