# Config validation, wildcard constraints, every path pattern and input function.
from pathlib import Path

from delta.config import validate_config

config = validate_config(
    config,
    schema_path=Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml",
    base_dir=Path.cwd(),
)

BODY = config["body_model"]


wildcard_constraints:
    model="anny|smplx",
    level="[0-9]",


# ------------------------------------------------------------------ paths
PATHS = {
    "anny_cache": BODY["anny"]["cache_dir"],
    "body_base": "resources/body/{model}.npz",
    "body_base_report": "results/body/{model}_convert.json",
    "body": "resources/body/{model}_sub{level}.npz",
    "body_summary": "results/body/{model}_sub{level}.json",
    "log": "logs/{rule}/{name}.log",
    "benchmark": "results/benchmarks/{rule}/{name}.tsv",
}


def log_path(rule, name="all"):
    return PATHS["log"].format(rule=rule, name=name)


def benchmark_path(rule, name="all"):
    return PATHS["benchmark"].format(rule=rule, name=name)


# ------------------------------------------------------- input functions
def body_model_file():
    """The upsampled body model every later stage reads."""
    return PATHS["body"].format(model=BODY["name"], level=BODY["upsample_level"])


def all_targets():
    return [
        body_model_file(),
        PATHS["body_summary"].format(model=BODY["name"], level=BODY["upsample_level"]),
    ]
