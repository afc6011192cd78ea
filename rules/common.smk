# Config validation, wildcard constraints, every path pattern and input function.
import json
import shlex
from pathlib import Path

from delta.config import SYNTHETIC_PEOPLESNAPSHOT_ROOT, check_device, data_source
from delta.config import (
    application_jobs,
    exterior_layers,
    exterior_source,
    motion_source,
    subject_ref,
)
from delta.config import subject_training as _subject_training
from delta.config import tracks_face as _tracks_face
from delta.config import validate_workflow_config
from delta.config import variant_training as _variant_training
from delta.applications.settings import AnimateSettings, ShowSettings
from delta.data import PROVIDES
from delta.eval.runtime import evaluation_minutes as _evaluation_minutes
from delta.eval.runtime import read_job as _read_render_job
from delta.eval.runtime import renders_minutes as _renders_minutes
from delta.eval.runtime import videos_minutes as _videos_minutes
from delta.eval.settings import EvalSettings
from delta.export.settings import ExportSettings
from delta.export.settings import part_settings as _export_part_settings
from delta.settings import from_mapping as _from_mapping
from delta.scene.settings import FRAME_BUDGET, set_keys, user_decided
from delta.synthetic.spec import (
    dressed_raw,
    parse_subject,
    reenacted_raw,
    reshaped_raw,
    truth_name,
)
from delta.training.presets import resolve as resolve_training, stage_view

# the one validation (delta validate-config runs the same): every problem before any job starts;
# the device is checked in onstart (Snakefile), once it is known whether jobs run here
config = validate_workflow_config(
    config,
    schema_path=Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml",
    base_dir=Path.cwd(),
    device=False,
    generated_roots=(SYNTHETIC_PEOPLESNAPSHOT_ROOT,),
)

BODY = config["body_model"]
PRE = config["preprocess"]
DATASETS = config["datasets"]
# the generated subjects: the synthetic dataset's and the People Snapshot stand-in's
SYNTHETIC_RAW = DATASETS.get("synthetic", {}).get("subjects", {}) | config["standins"]
SYNTHETIC = {name: parse_subject(name, raw) for name, raw in SYNTHETIC_RAW.items()}


# The generated truth of each application on a synthetic subject (docs/applications.md): the subject wearing
# the other's exterior, or with its phenotype edited. Named with a '.', which no configured subject has.
def application_truths():
    out = {}
    for d, s, e in application_jobs(config, "dress"):
        wearer = exterior_source(config, e)[1]
        if s in SYNTHETIC_RAW and wearer in SYNTHETIC_RAW:
            out[("dress", s, e)] = (
                truth_name("dress", s, e),
                dressed_raw(
                    SYNTHETIC_RAW[s], SYNTHETIC_RAW[wearer], exterior_layers(config, e)
                ),
            )
    for d, s, e in application_jobs(config, "reshape"):
        edit = config["applications"]["shapes"][e]
        phenotype_only = not any(k.startswith("beta") for k in edit)
        if s in SYNTHETIC_RAW and phenotype_only and BODY["name"] == "anny":
            out[("reshape", s, e)] = (
                truth_name("reshape", s, e),
                reshaped_raw(SYNTHETIC_RAW[s], edit),
            )
    for d, s, driver in application_jobs(config, "reenact"):
        drives = subject_ref(config, config["applications"]["drivers"][driver])
        if s in SYNTHETIC_RAW and drives is not None and drives[1] in SYNTHETIC_RAW:
            out[
                ("reenact", s, driver)
            ] = (  # delta reenact's default anchor and reference: frame 0
                truth_name("reenact", s, driver),
                reenacted_raw(SYNTHETIC_RAW[s], SYNTHETIC_RAW[drives[1]]),
            )
    return out


APPLICATION_TRUTHS = application_truths()
SYNTHETIC_RAW = SYNTHETIC_RAW | {name: raw for name, raw in APPLICATION_TRUTHS.values()}
SYNTHETIC |= {
    name: parse_subject(name, raw) for name, raw in APPLICATION_TRUTHS.values()
}


wildcard_constraints:
    model="anny|smplx",
    level="[0-9]",
    subject="[A-Za-z0-9_.-]+",
    dataset="[A-Za-z0-9_-]+",
    stage="[12]",
    variant="[A-Za-z0-9_.-]+",
    motion="[A-Za-z0-9_-]+",
    exterior="[A-Za-z0-9_-]+",
    shape="[A-Za-z0-9_-]+",


# ------------------------------------------------------------------ paths
PATHS = {
    "anny_cache": BODY["anny"]["cache_dir"],
    "body_base": "resources/body/{model}.npz",
    "body_base_report": "results/body/{model}_convert.json",
    "body": "resources/body/{model}_sub{level}.npz",
    "body_summary": "results/body/{model}_sub{level}.json",
    "anny_shape_space": "resources/body/anny_pca.npz",
    "anny_expressions": "resources/body/anny_expressions.npz",
    "face_body": "resources/body/{model}_sub{level}_face.npz",
    "face_embedding": "resources/body/{model}_sub{level}_face_landmarks.npz",
    # synthetic captures: the video is all a real capture has; ground truth lies apart in gt/
    "syn_video": "data/synthetic/{subject}/{subject}.mp4",
    "syn_params": "data/synthetic/{subject}/gt/params.npz",
    "syn_frames": "data/synthetic/{subject}/gt/frames.h5",
    "syn_meshes": "data/synthetic/{subject}/gt/meshes.h5",
    "syn_splits": "data/synthetic/{subject}/gt/splits.json",
    # the same captures in People Snapshot's layout: a People Snapshot root anyone can generate
    "syn_ps_dir": f"{SYNTHETIC_PEOPLESNAPSHOT_ROOT}/{{subject}}",
    "record": "results/{dataset}/{subject}/frames.h5",
    "matting": "results/{dataset}/{subject}/matting.h5",
    "keypoints": "results/{dataset}/{subject}/keypoints.h5",
    "mediapipe_pose": f"{PRE['models_dir']}/mediapipe/pose_landmark_full.onnx",
    "mediapipe_face": f"{PRE['models_dir']}/mediapipe/face_landmark.onnx",
    "mediapipe_detector": f"{PRE['models_dir']}/mediapipe/face_detection_short_range.onnx",
    "parsing": "results/{dataset}/{subject}/parsing.h5",
    "record_summary": "results/{dataset}/{subject}/frames.json",
    "init_params": "results/{dataset}/{subject}/init/params.npz",
    "init_report": "results/{dataset}/{subject}/init/report.csv",
    "scene": "results/{dataset}/{subject}/scene.json",
    "stage_dir": "results/{dataset}/{subject}/stage{stage}",
    "stage_model": "results/{dataset}/{subject}/stage{stage}/model.pt",
    "stage_losses": "results/{dataset}/{subject}/stage{stage}/losses.csv",
    "loss_plot": "results/{dataset}/{subject}/stage{stage}/losses.png",
    "eval_metrics": "results/{dataset}/{subject}/eval/metrics.csv",
    "eval_summary": "results/{dataset}/{subject}/eval/summary.json",
    "eval_worst": "results/{dataset}/{subject}/eval/worst",
    "export_dir": "results/{dataset}/{subject}/export",
    "export_json": "results/{dataset}/{subject}/export/export.json",
    "export_meshes": "results/{dataset}/{subject}/export/meshes.json",
    "export_glb": "results/{dataset}/{subject}/export/avatar.glb",
    "export_animated": "results/{dataset}/{subject}/export/avatar_animated.glb",
    "turntable": "results/{dataset}/{subject}/export/turntable.mp4",
    "novel_pose": "results/{dataset}/{subject}/export/novel_pose.mp4",
    "sidebyside": "results/{dataset}/{subject}/export/sidebyside",
    "dataset_metrics": "results/{dataset}/metrics.csv",
    "animate_dir": "results/{dataset}/{subject}/animate/{motion}",
    "animation": "results/{dataset}/{subject}/animate/{motion}/animation.mp4",
    "animation_json": "results/{dataset}/{subject}/animate/{motion}/animation.json",
    "animation_glb": "results/{dataset}/{subject}/animate/{motion}/animation.glb",
    "reenact_dir": "results/{dataset}/{subject}/reenact/{driver}",
    "reenactment": "results/{dataset}/{subject}/reenact/{driver}/reenactment.mp4",
    "reenact_json": "results/{dataset}/{subject}/reenact/{driver}/reenactment.json",
    "reenact_scores": "results/{dataset}/{subject}/reenact/{driver}/scores.csv",
    "dress_dir": "results/{dataset}/{subject}/dress/{exterior}",
    "dressed": "results/{dataset}/{subject}/dress/{exterior}/dressed.png",
    "dressed_turntable": "results/{dataset}/{subject}/dress/{exterior}/turntable.mp4",
    "dress_json": "results/{dataset}/{subject}/dress/{exterior}/dress.json",
    "reshape_dir": "results/{dataset}/{subject}/reshape/{shape}",
    "reshaped": "results/{dataset}/{subject}/reshape/{shape}/reshaped.png",
    "reshaped_turntable": "results/{dataset}/{subject}/reshape/{shape}/turntable.mp4",
    "reshape_json": "results/{dataset}/{subject}/reshape/{shape}/reshape.json",
    "dress_scores": "results/{dataset}/{subject}/dress/{exterior}/scores.csv",
    "tryon_dir": "results/{dataset}/{subject}/tryon/{exterior}",
    "tryon": "results/{dataset}/{subject}/tryon/{exterior}/tryon.png",
    "tryon_turntable": "results/{dataset}/{subject}/tryon/{exterior}/turntable.mp4",
    "tryon_json": "results/{dataset}/{subject}/tryon/{exterior}/tryon.json",
    "reshape_scores": "results/{dataset}/{subject}/reshape/{shape}/scores.csv",
    "application_scores": "results/{dataset}/applications.csv",
    "perceptual_vgg": f"{config['training']['perceptual_dir']}/vgg_shift_tolerant.pth",
    "perceptual_alex": f"{config['training']['perceptual_dir']}/alex_shift_tolerant.pth",
    "log": "logs/{rule}/{name}.log",
    "benchmark": "results/benchmarks/{rule}/{name}.tsv",
}


def log_path(rule, name="all"):
    return PATHS["log"].format(rule=rule, name=name)


def benchmark_path(rule, name="all"):
    return PATHS["benchmark"].format(rule=rule, name=name)


# ------------------------------------------------------- input functions
def subject_framing(wildcards):
    """A video subject's framing (``datasets.*.subjects.*.framing``): ``head`` for a head-and-shoulders
    close-up, whose face the model steps track; ``full`` otherwise and for other datasets.
    """
    dataset, subject = wildcards.get("dataset"), wildcards.get("subject")
    if dataset not in DATASETS or dataset_kind(dataset) != "video":
        return "full"
    return (DATASETS[dataset]["subjects"].get(subject) or {}).get("framing", "full")


def tracks_face(wildcards):
    """A subject whose face is tracked and modelled: a synthetic talking face (its record carries face
    points), or a video's head close-up (its face-mesh landmarks placed on the body mesh).
    """
    dataset, subject = wildcards.get("dataset"), wildcards.get("subject")
    if dataset not in DATASETS or subject not in DATASETS[dataset]["subjects"]:
        return False
    return _tracks_face(config, dataset, subject)


def head_models(wildcards):
    """The face models a head close-up's steps track it with (beside the pose model); none otherwise."""
    if subject_framing(wildcards) != "head":
        return []
    return [PATHS["mediapipe_detector"], PATHS["mediapipe_face"]]


def face_embedding(wildcards):
    """The face-mesh landmarks' places on the body mesh, for a video's head close-up; nothing otherwise."""
    if subject_framing(wildcards) != "head":
        return []
    return PATHS["face_embedding"].format(
        model=BODY["name"], level=BODY["upsample_level"]
    )


def embedding_body(wildcards):
    """The body model the face-mesh landmarks are calibrated on: with Anny's facial actions where the model
    is Anny (the calibration faces open their jaw, so the inner lips' points find their own lip).
    """
    key = "face_body" if wildcards.model == "anny" else "body"
    return PATHS[key].format(model=wildcards.model, level=wildcards.level)


def body_model_file(wildcards=None):
    """The upsampled body model a subject's stages read: with the expression space for a tracked face
    (Anny's facial actions attached), without it for everyone else."""
    level = BODY["upsample_level"]
    if wildcards is not None and BODY["name"] == "anny" and tracks_face(wildcards):
        return PATHS["face_body"].format(model="anny", level=level)
    return PATHS["body"].format(model=BODY["name"], level=level)


def anny_model_file():
    """Synthetic captures are built on the Anny model at the configured upsampling level."""
    return PATHS["body"].format(model="anny", level=BODY["upsample_level"])


def synthetic_spec_json(wildcards):
    return json.dumps(SYNTHETIC_RAW[wildcards.subject], sort_keys=True)


def synthetic_expressions(wildcards):
    """The expression space a subject's talking face needs (nothing for a still face)."""
    if SYNTHETIC[wildcards.subject].expressions == "none":
        return []
    return PATHS["anny_expressions"]


def peoplesnapshot_files(subject):
    d = PATHS["syn_ps_dir"].format(subject=subject)
    return [
        f"{d}/{subject}.mp4",
        f"{d}/masks.hdf5",
        f"{d}/camera.pkl",
        f"{d}/keypoints.hdf5",
    ]


def synthetic_targets():
    out = []
    truths = {name for name, _ in APPLICATION_TRUTHS.values()}
    for name, spec in SYNTHETIC.items():
        if name in truths:
            continue
        out += [
            PATHS[k].format(subject=name)
            for k in ("syn_video", "syn_params", "syn_frames", "syn_splits")
        ]
        if name in config["standins"]:  # People Snapshot's stand-in: its layout too
            out += peoplesnapshot_files(name)
    return out


def dataset_kind(dataset):
    return "synthetic" if dataset == "synthetic" else DATASETS[dataset]["kind"]


def prepare_inputs(wildcards):
    """What the frame record of a subject is made from, by dataset kind."""
    kind = dataset_kind(wildcards.dataset)
    steps = step_files(wildcards)
    if kind == "synthetic":
        files = ("syn_video", "syn_params", "syn_frames", "syn_splits")
        return {k: PATHS[k].format(subject=wildcards.subject) for k in files} | steps
    if kind == "video":
        embedding = face_embedding(wildcards)
        return (
            {"video": video_input(wildcards)}
            | steps
            | ({"face_embedding": embedding} if embedding else {})
        )
    root = Path(DATASETS[wildcards.dataset]["root"]) / wildcards.subject
    return steps | {
        "video": str(root / f"{wildcards.subject}.mp4"),
        "masks": str(root / "masks.hdf5"),
        "camera": str(root / "camera.pkl"),
        "dataset_keypoints": str(
            root / "keypoints.hdf5"
        ),  # beside a keypoint step's file
    }


def used_provided(dataset):
    """The dataset annotations the config uses; model steps produce the rest."""
    ships = PROVIDES[dataset_kind(dataset)]
    return [a for a in ships if a in DATASETS[dataset].get("use_provided", ships)]


def needs_parsing(dataset):
    wanted = {
        "default": {"clothing"},
        "u2net_cloth": {"clothing"},
        "bisenet_face": {"hair", "skin"},
    }.get(PRE["parsing"]["model"], set())
    return bool(wanted - set(used_provided(dataset)))


def step_files(wildcards):
    files = {}
    if "person" not in used_provided(wildcards.dataset):
        files["matting"] = PATHS["matting"].format(**wildcards)
    if needs_parsing(wildcards.dataset):
        files["parsing"] = PATHS["parsing"].format(**wildcards)
    wanted = PRE["face_landmarks"] or (
        PRE["keypoint_depth"] and subject_framing(wildcards) != "head"
    )
    if "keypoints" not in used_provided(wildcards.dataset) or wanted:
        files["keypoints"] = PATHS["keypoints"].format(**wildcards)
    return files


def parsed_person(wildcards):
    """The matting step's file where it runs for the subject: the default parser partitions its person."""
    if PRE["parsing"]["model"] != "default":
        return []
    return step_files(wildcards).get("matting", [])


def _step_model(step, default_model):
    """The ONNX file a step runs: the converted MediaPipe model for the defaults, else the user's export."""
    m = PRE[step]
    if m["model"] == "none":
        return []
    return PATHS["mediapipe_pose"] if m["model"] == default_model else m["path"]


def matting_model():
    return _step_model("matting", "mediapipe")


def parsing_model():
    return _step_model("parsing", "default")


def video_input(wildcards):
    kind = dataset_kind(wildcards.dataset)
    if kind == "synthetic":
        return PATHS["syn_video"].format(subject=wildcards.subject)
    root = Path(DATASETS[wildcards.dataset]["root"])
    return str(
        (root / wildcards.subject if kind == "peoplesnapshot" else root)
        / f"{wildcards.subject}.mp4"
    )


def step_selection(wildcards):
    """The model steps' frame selection flags: a video subject's ranges and preprocess.max_frames (they
    analyse only the frames the record keeps); none for other datasets (every frame)."""
    if dataset_kind(wildcards.dataset) != "video":
        return []
    ranges = DATASETS[wildcards.dataset]["subjects"][wildcards.subject] or {}
    return [
        "--frames",
        json.dumps({k: v for k, v in ranges.items() if k in ("train", "test")}),
        "--max-frames",
        json.dumps(PRE["max_frames"]),
        "--framing",
        subject_framing(wildcards),
    ]


def prepare_root(wildcards):
    """The folder the dataset adapter reads."""
    if dataset_kind(wildcards.dataset) == "synthetic":
        return str(Path(PATHS["syn_video"].format(subject=wildcards.subject)).parent)
    return DATASETS[wildcards.dataset]["root"]


def prepare_settings(wildcards):
    """A frame record's job, as JSON: the adapter, the image size and margin, the subject's frames."""
    kind = dataset_kind(wildcards.dataset)
    frames = (
        {}
        if kind == "synthetic"
        else {
            k: v
            for k, v in (
                DATASETS[wildcards.dataset]["subjects"][wildcards.subject] or {}
            ).items()
            if k in ("train", "test")
        }
    )
    return json.dumps(
        {"kind": kind, "resolution": PRE["resolution"], "crop_margin": PRE["crop_margin"],
         "score_size": PRE["score_size"], "frames": frames, "max_frames": PRE["max_frames"],
         "use_provided": [a for a in used_provided(wildcards.dataset) if a != "face_points" or tracks_face(wildcards)]},
        sort_keys=True,
    )  # fmt: skip


def record_targets():
    return [
        PATHS[k].format(dataset=d, subject=s, stage=2)
        for d, spec in DATASETS.items()
        for s in spec["subjects"]
        for k in ("record", "init_params", "stage_model")
    ]


# ------------------------------------------------------------- init fitting
FIT = config["fitting"]


def subject_fit_settings(subject):
    """[settings, subject's own] FitConfig overrides of a subject."""
    return [FIT["settings"], FIT["subjects"].get(subject, {})]


def fit_settings_json(wildcards):
    return json.dumps(subject_fit_settings(wildcards.subject), sort_keys=True)


# ------------------------------------------------------------- training
TRAIN = config["training"]


def subject_training(subject):
    """(preset, [overrides...]) of a subject: the config's preset and overrides, then the subject's own."""
    return _subject_training(config, subject)


def subject_settings(subject):
    preset, overrides = subject_training(subject)
    return resolve_training(preset, *overrides)


TRAINING = {
    s: subject_settings(s) for spec in DATASETS.values() for s in spec["subjects"]
}


def wildcard_training(wildcards):
    """(preset, [overrides...]) of a main-run stage, or of a sweep variant's when the wildcards name one."""
    if "variant" in wildcards.keys():
        return variant_training(wildcards.subject, wildcards.variant)
    return subject_training(wildcards.subject)


def stage_training(wildcards):
    """A training job's whole configuration, as JSON: the preset, the resolved settings the stage reads,
    and which of the keys the scene analysis decides the config sets itself (only those: a key
    the scene never decides, say stage 2's, must not rerun stage 1).
    """
    preset, overrides = wildcard_training(wildcards)
    raw = resolve_training(preset, *overrides).raw
    return json.dumps(
        {
            "preset": preset,
            "user_set": user_decided(set_keys(overrides), int(wildcards.stage)),
            **stage_view(raw, int(wildcards.stage)),
        },
        sort_keys=True,
    )


def scene_settings_json(wildcards):
    """The configured room and samples of a subject's exterior (the scene analysis's floor and spacing),
    its stage 1's rays (the most the scene may give) and its colour grids (what a pattern is measured against).
    """
    st = TRAINING[wildcards.subject]
    render = st.avatar.render
    return json.dumps(
        {
            "max_dist": render.max_dist,
            "samples": render.samples,
            "rays": st.stage1.rays,
            "max_rays": st.stage1.max_rays,
            "color_res": st.avatar.nerf.colour_nodes() if st.avatar.nerf else 0,
            "nerf_margin": st.avatar.nerf_margin,
        },
        sort_keys=True,
    )


def train_inputs(wildcards):
    """Stage 1 starts from the init fit; stage 2 from stage 1's model (and the VGG weights of its semantic loss)."""
    w = dict(wildcards)
    files = {"record": PATHS["record"].format(**w), "body": body_model_file(wildcards),
             "scene": PATHS["scene"].format(dataset=w["dataset"], subject=w["subject"])}  # fmt: skip
    if wildcards.stage == "1":
        files["start"] = PATHS["init_params"].format(**w)
        return files
    model = "variant_model" if "variant" in wildcards.keys() else "stage_model"
    files["start"] = PATHS[model].format(**{**w, "stage": 1})
    st = resolve_training(
        *[wildcard_training(wildcards)[0]] + wildcard_training(wildcards)[1]
    )
    if st.semantic != "none" and st.weights.semantic > 0:
        files["vgg"] = PATHS["perceptual_vgg"]
    return files


def train_mem_mb(wildcards, attempt):
    """~1.5 GB besides the frames, which the scene analysis sizes to at most FRAME_BUDGET bytes (the
    capture's own size; a config's resolution, as bytes, below it); grows with the rays a step.
    """
    st = TRAINING[wildcards.subject]
    return _grow(1500 + FRAME_BUDGET / 2**20 + 0.5 * st.stage1.rays, attempt)


def train_runtime(wildcards, attempt):
    """Minutes: ~0.6 s a step at the fast preset on 2 cores, times 3 (a step's cost grows with its rays
    and samples, not with the frames' size)."""
    st = TRAINING[wildcards.subject]
    cfg = st.stage1 if wildcards.stage == "1" else st.stage2
    scale = cfg.rays / 1024 * st.avatar.render.samples / 24
    return int(10 + attempt * 3 * cfg.iterations * 0.6 * scale / 60)


def all_targets():
    return (
        [
            body_model_file(),
            PATHS["body_summary"].format(
                model=BODY["name"], level=BODY["upsample_level"]
            ),
        ]
        + synthetic_targets()
        + record_targets()
        + dataset_metrics_targets()
        + application_targets()
    )


# ------------------------------------------------------------ resources
# Callables so that local and cluster runs use the same figures; memory grows with each retry.
def _grow(mb, attempt):
    return int(mb * (1 + 0.5 * (attempt - 1)))


def synth_mem_mb(wildcards, attempt):
    """~1.3 GB measured for a 512² subject; scales with the image area."""
    res = SYNTHETIC[wildcards.subject].resolution
    return _grow(1200 + 0.004 * res * res, attempt)


def synth_runtime(wildcards, attempt):
    """Minutes: ~0.8 s a 512² frame on 2 cores, times 3 for slower nodes."""
    spec = SYNTHETIC[wildcards.subject]
    return int(
        5 + attempt * 3 * spec.num_frames * 0.8 * (spec.resolution / 512) ** 2 / 60
    )


def prepare_mem_mb(wildcards, attempt):
    return _grow(1500 + 0.01 * PRE["resolution"] ** 2, attempt)


def train_gpu_resources():
    """What a training job asks for besides CPUs: one GPU (of ``cluster.gpu_model`` if set) where the config
    says cuda; ``auto`` asks for none and uses a GPU only where the node has one."""
    if config["device"] != "cuda":
        return {}
    model = config["cluster"]["gpu_model"]
    return {"gpu": 1, **({"gpu_model": model} if model else {})}


# ------------------------------------------------ evaluation and export
EVAL = config["evaluation"]
EXPORT = config["export"]


def configured(wildcards):
    """Fail at DAG construction, naming what is configured, when a target names anything else."""
    if wildcards.dataset not in DATASETS:
        raise ValueError(
            f"dataset '{wildcards.dataset}' is not configured; configured datasets: {sorted(DATASETS)}"
        )
    subjects = DATASETS[wildcards.dataset]["subjects"]
    if "subject" in wildcards.keys() and wildcards.subject not in subjects:
        raise ValueError(f"subject '{wildcards.subject}' is not configured for dataset '{wildcards.dataset}'; "
                         f"configured subjects: {sorted(subjects)}")  # fmt: skip
    return []


def evaluated_model(wildcards):
    configured(wildcards)
    return PATHS["stage_model"].format(stage=EVAL["stage"], **wildcards)


def trained_inputs(wildcards):
    """What export and evaluation read: the evaluated stage's model, its frames and the body model."""
    return {
        "model": evaluated_model(wildcards),
        "record": PATHS["record"].format(**wildcards),
        "body": body_model_file(wildcards),
    }


def eval_inputs(wildcards):
    files = trained_inputs(wildcards) | {"alex": PATHS["perceptual_alex"]}
    if (
        dataset_kind(wildcards.dataset) == "synthetic"
        or wildcards.subject in config["standins"]
    ):  # ground truth for the geometry columns
        files["gt"] = PATHS["syn_meshes"].format(subject=wildcards.subject)
        files["export"] = PATHS["export_meshes"].format(**wildcards)
    return files


def eval_settings(wildcards, settings=None):
    """The evaluation section a job scores with, as JSON: every knob of ``delta evaluate`` at once."""
    return json.dumps(settings or EVAL, sort_keys=True)


def eval_truth(wildcards, input):
    """Where the synthetic ground truth is (the geometry columns): options of ``delta evaluate``."""
    args = []
    if "gt" in input.keys():
        args += ["--gt-meshes", input.gt]
    if "export" in input.keys():
        args += ["--export-dir", str(Path(input.export).parent)]
    return args


EVAL_SETTINGS = _from_mapping(EvalSettings, EVAL, "evaluation")
EXPORT_SETTINGS = _from_mapping(ExportSettings, EXPORT, "export")


def render_job(input, model="model"):
    """What a job renders with (the record's whole frames, the samples of ``model``'s stage); None in a
    dry run, before the files exist: Snakemake evaluates the resources again before the job runs.
    """
    return _read_render_job(input.record, Path(input[model]).with_name("settings.json"))


def eval_runtime(wildcards, input, attempt):
    """Minutes: the scored frames' renders and refinement steps (delta.eval.runtime)."""
    return _evaluation_minutes(render_job(input), EVAL_SETTINGS, attempt)


def videos_runtime(wildcards, input, attempt):
    """Minutes: the export's whole-frame renders (delta.eval.runtime)."""
    return _videos_minutes(render_job(input), EXPORT_SETTINGS, attempt)


def application_runtime(renders, fallback, model="model", scored=None):
    """A resource function of an application job: ``renders(input)`` whole frames at one ray a pixel and
    ``scored(input)`` (renders, supersample) against a truth; the job's frames and ``model``'s samples.
    """

    def minutes(wildcards, input, attempt):
        count = renders(input)  # None: unknown before the job (a motion's whole length)
        job = render_job(input, model) if count is not None else None
        more, ss = scored(input) if scored is not None else (0, 1)
        return _renders_minutes(job, count or 0, attempt, more, ss, fallback)

    return minutes


def show_scored(settings):
    """An edit scored against its truth: each scored frame as trained and edited, supersampled."""
    return lambda input: (
        (2 * settings.score_frames, settings.supersample)
        if "truth" in input.keys()
        else (0, 1)
    )


def shown(settings):
    """An edit shown: the frame as trained and edited, and the turntable."""
    return lambda input: 2 + settings.turntable_frames


def at_most(count):
    """A job rendering ``count`` frames (0: all of a motion, unknown before it runs)."""
    return lambda input: count or None


def export_settings(part):
    """The export settings one part's job reads, as JSON (a change to the others does not rerun it)."""
    return json.dumps(_export_part_settings(EXPORT, part), sort_keys=True)


def dataset_subjects(wildcards):
    configured(wildcards)
    return list(DATASETS[wildcards.dataset]["subjects"])


def aggregate_inputs(wildcards):
    subjects = dataset_subjects(wildcards)
    fmt = lambda key, **kw: [
        PATHS[key].format(dataset=wildcards.dataset, subject=s, **kw) for s in subjects
    ]  # noqa: E731
    return {
        "summaries": fmt("eval_summary"),
        "exports": fmt("export_json"),
        "plots": fmt("loss_plot", stage=1) + fmt("loss_plot", stage=2),
        "bench1": [
            benchmark_path("train", f"{wildcards.dataset}_{s}_stage1") for s in subjects
        ],
        "bench2": [
            benchmark_path("train", f"{wildcards.dataset}_{s}_stage2") for s in subjects
        ],
    }


def aggregate_benchmarks(wildcards, input):
    subjects = dataset_subjects(wildcards)
    pairs = [f"{s}/stage1={b}" for s, b in zip(subjects, input.bench1)]
    pairs += [f"{s}/stage2={b}" for s, b in zip(subjects, input.bench2)]
    return pairs


def application_targets():
    return (
        [
            PATHS["animation"].format(dataset=d, subject=s, motion=m)
            for d, s, m in application_jobs(config, "animate")
        ]
        + [
            PATHS["dressed"].format(dataset=d, subject=s, exterior=e)
            for d, s, e in application_jobs(config, "dress")
        ]
        + [
            PATHS["reshaped"].format(dataset=d, subject=s, shape=e)
            for d, s, e in application_jobs(config, "reshape")
        ]
        + [
            PATHS["tryon"].format(dataset=d, subject=s, exterior=e)
            for d, s, e in application_jobs(config, "tryon")
        ]
        + [
            PATHS["reenactment"].format(dataset=d, subject=s, driver=r)
            for d, s, r in application_jobs(config, "reenact")
        ]
        + [
            PATHS["application_scores"].format(dataset=d)
            for d in sorted({d for d, _, _ in scored_jobs()})
        ]
    )


def scored_jobs():
    """(dataset, subject, scores.csv) of the application jobs that have a generated truth."""
    out = []
    for app, key, wildcard in (
        ("dress", "dress_scores", "exterior"),
        ("reshape", "reshape_scores", "shape"),
        ("reenact", "reenact_scores", "driver"),
    ):
        for d, s, e in application_jobs(config, app):
            if (app, s, e) in APPLICATION_TRUTHS:
                path = PATHS[key].format(dataset=d, subject=s, **{wildcard: e})
                out.append((d, s, path))
    return out


def application_score_inputs(wildcards):
    return [path for d, _, path in scored_jobs() if d == wildcards.dataset]


ANIMATE = config["applications"]["animate"]["settings"]
ANIMATE_SETTINGS = _from_mapping(
    AnimateSettings, ANIMATE, "applications.animate.settings"
)


def animate_inputs(wildcards):
    """The avatar, the motion (a file, or another subject's fit) and, when meshes are written, the export
    whose clothing surface is posed."""
    files = trained_inputs(wildcards)
    source = motion_source(config, wildcards.motion)
    if isinstance(source, tuple):
        files["motion"] = PATHS["init_params"].format(
            dataset=source[0], subject=source[1]
        )
    else:
        files["motion"] = source
    if ANIMATE["meshes"]:
        files["export"] = PATHS["export_meshes"].format(**wildcards)
    return files


DRESS = config["applications"]["dress"]["settings"]
DRESS_SETTINGS = _from_mapping(ShowSettings, DRESS, "applications.dress.settings")


def truth_inputs(wildcards, application, name, wearer=None, meshes=True):
    """The generated truth of an application job, the ST-LPIPS weights and the exports whose clothing
    surfaces are measured against it (the avatar's, and the wearer's; ``meshes``), where it has a truth.
    """
    truth = APPLICATION_TRUTHS.get((application, wildcards.subject, name))
    if truth is None:
        return {}
    files = {
        "truth": PATHS["syn_params"].format(subject=truth[0]),
        "alex": PATHS["perceptual_alex"],
    }
    if meshes:
        files["export"] = PATHS["export_meshes"].format(**wildcards)
    if wearer is not None:
        files["wearer_export"] = PATHS["export_meshes"].format(**wearer)
    return files


def truth_args(wildcards, input):
    if "truth" not in input.keys():
        return []
    ply = lambda key: str(
        Path(input[key]).parent / "clothing_nerf_space.ply"
    )  # noqa: E731
    args = ["--truth", str(Path(input.truth).parent.parent)]
    args += ["--perceptual", str(Path(input.alex).parent), "--clothing", ply("export")]
    if "wearer_export" in input.keys():
        args += ["--wearer-clothing", ply("wearer_export")]
    return args


def dress_inputs(wildcards):
    """The body avatar, the avatar whose exterior it wears and, on synthetic subjects, the truth."""
    dataset, subject = exterior_source(config, wildcards.exterior)
    theirs = {"dataset": dataset, "subject": subject}
    return (
        trained_inputs(wildcards)
        | {
            "wearer_model": PATHS["stage_model"].format(stage=EVAL["stage"], **theirs),
            "wearer_record": PATHS["record"].format(**theirs),
            "wearer_body": body_model_file(theirs),
        }
        | truth_inputs(wildcards, "dress", wildcards.exterior, theirs)
    )


RESHAPE = config["applications"]["reshape"]["settings"]
RESHAPE_SETTINGS = _from_mapping(ShowSettings, RESHAPE, "applications.reshape.settings")


def reshape_inputs(wildcards):
    """The avatar and, for Anny, its shape space (phenotype edits are made in it)."""
    files = trained_inputs(wildcards)
    if BODY["name"] == "anny":
        files["shape_space"] = PATHS["anny_shape_space"]
    return files | truth_inputs(wildcards, "reshape", wildcards.shape)


def reshape_args(wildcards, input):
    edit = json.dumps(config["applications"]["shapes"][wildcards.shape], sort_keys=True)
    args = ["--edit", edit]
    if "shape_space" in input.keys():
        args += [
            "--shape-space",
            input.shape_space,
            "--anny-cache",
            PATHS["anny_cache"],
        ]
    return args


TRYON = config["applications"]["tryon"]
TRYON_SETTINGS = _from_mapping(
    ShowSettings, TRYON["settings"], "applications.tryon.settings"
)


def layer_args(wildcards):
    """``--layers ...`` of an exterior that is some layers of an avatar's (``dataset/subject:hair``)."""
    layers = exterior_layers(config, wildcards.exterior)
    return ["--layers", *layers] if layers else []


def tryon_inputs(wildcards):
    """The capture's frames and init fit (no training), and the avatar whose exterior is tried on."""
    dataset, subject = exterior_source(config, wildcards.exterior)
    theirs = {"dataset": dataset, "subject": subject}
    return {
        "record": PATHS["record"].format(**wildcards),
        "init": PATHS["init_params"].format(**wildcards),
        "body": body_model_file(wildcards),
        "wearer_model": PATHS["stage_model"].format(stage=EVAL["stage"], **theirs),
        "wearer_record": PATHS["record"].format(**theirs),
        "wearer_body": body_model_file(theirs),
    }


REENACT = config["applications"]["reenact"]


def reenact_scored(input):
    """A reenactment scored against its truth: each scored frame still, driven and truly driven."""
    if "truth" not in input.keys():
        return (0, 1)
    return (3 * REENACT["score_frames"], REENACT["supersample"])


def reenact_inputs(wildcards):
    """The avatar and the driving avatar (each its evaluated stage's model and its frames)."""
    dataset, subject = subject_ref(
        config, config["applications"]["drivers"][wildcards.driver]
    )
    driver = {"dataset": dataset, "subject": subject}  # validated with the config
    return (
        trained_inputs(wildcards)
        | {
            "driver_model": PATHS["stage_model"].format(stage=EVAL["stage"], **driver),
            "driver_record": PATHS["record"].format(**driver),
        }
        | truth_inputs(wildcards, "reenact", wildcards.driver, meshes=False)
    )


def reenact_truth_args(wildcards, input):
    """Where a reenactment has a generated truth: what scores it (scores.csv)."""
    if "truth" not in input.keys():
        return []
    return [
        "--truth",
        str(Path(input.truth).parent.parent),
        "--perceptual",
        str(Path(input.alex).parent),
        "--score-frames",
        str(REENACT["score_frames"]),
        "--supersample",
        str(REENACT["supersample"]),
    ]


def animate_clothing(wildcards, input):
    if "export" not in input.keys():
        return []
    return ["--clothing", str(Path(input.export).parent / "clothing_nerf_space.ply")]


def dataset_metrics_targets():
    return [PATHS["dataset_metrics"].format(dataset=d) for d in DATASETS]
