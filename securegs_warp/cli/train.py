"""``securegs train`` (plain Scaffold-GS, or plain 3DGS with ``--model 3dgs``) and the commands on a
saved model: ``render``, ``eval``, ``export``. The last three load the model and the scene's cameras only: no trainer, no optimizer."""
from __future__ import annotations

import torch

from ..config import RunConfig, from_dict
from ..evaluation import evaluate_views
from ..gaussians import GaussianModel
from ..io import export_3dgs_ply
from ..runs import RunFolder, folder_size_mb, png_name, save_png
from ..scaffold_model import ScaffoldModel
from .common import (
    HEAD_FLAGS,
    SCENE_FLAGS,
    TRAIN_FLAGS,
    CommandError,
    add_config_flags,
    add_run_arguments,
    check_run_arguments,
    config_from_args,
    prepare_run,
    print_metrics,
    quiet_warp,
    resolve_device,
    start_training,
)

TRAIN_DEFAULTS = {"train.iterations": 800}
MODEL_FLAGS = (
    ("--model", "train.model", "what to train: scaffold (Scaffold-GS) or 3dgs (plain 3DGS, saved as a standard 3DGS "
                               "PLY)"),
    ("--sh-degree", "train.gaussians.sh_degree", "3dgs: largest spherical-harmonic degree of the colours"),
)


def cmd_train(args) -> int:
    from ..train import GaussianTrainer, ScaffoldTrainer

    check_run_arguments(args)
    device = resolve_device(args.device)
    config = config_from_args(args, RunConfig(), TRAIN_DEFAULTS, device)
    quiet_warp()
    run = RunFolder(args.out)
    resume = prepare_run(run, config, args)
    trainer_class = GaussianTrainer if config.train.model == "3dgs" else ScaffoldTrainer
    trainer = trainer_class(config.scene.load(), config.train, device=device)

    def finish():
        trainer.model.save(run.model)
        metrics = evaluate_model(trainer.model, trainer.scene, config, run, device)
        metrics.update(**trainer.size_stats(), train_seconds=round(trainer.train_seconds, 2))
        run.write_json(run.metrics, metrics)
        print_metrics(metrics)

    return start_training(trainer, run, config, resume, args, finish)


def background_of(scene, device) -> torch.Tensor | None:
    return None if scene.background is None else torch.tensor(scene.background, dtype=torch.float32, device=device)


def evaluate_model(model: ScaffoldModel | GaussianModel, scene, config: RunConfig, run: RunFolder, device) -> dict:
    """Held-out metrics (``scene.evaluation_views``) and FPS of the public render; writes the renders as PNGs."""
    background = background_of(scene, device)

    def render(cam):  # a training view (no view held out) with its own appearance row
        return model.render(cam, config.train.raster, background=background, camera_index=scene.camera_index(cam))

    cams = scene.evaluation_views
    with torch.no_grad():
        metrics = evaluate_views(render, cams, device, with_lpips=True,
                                 on_render=lambda cam, image: save_png(run.renders / png_name(cam.name), image))
    # "split": "train" where the scene holds no view out, so the figures are not held-out ones.
    return {**metrics, "split": scene.evaluation_split, "size_mb": round(folder_size_mb(run.model), 3),
            "device": str(device)}


def load_run(path, device) -> tuple[ScaffoldModel | GaussianModel, RunConfig, RunFolder]:
    """The saved public model of a finished run (``train`` or ``hide``), its config and folder."""
    quiet_warp()
    run = RunFolder(path)
    config = from_dict(RunConfig, run.read_config())
    if not run.model.is_dir():
        raise CommandError(f"{run.path} has no saved model yet (the run has not finished: --resume it)")
    model_class = GaussianModel if config.train.model == "3dgs" else ScaffoldModel
    return model_class.load(run.model, device=device), config, run


def cmd_render(args) -> int:
    device = resolve_device(args.device)
    model, config, run = load_run(args.run, device)
    scene = config.scene.load()
    cams = scene.test if args.split == "test" else scene.train
    out = RunFolder(args.out) if args.out else run
    background = background_of(scene, device)
    with torch.no_grad():
        for cam in cams:
            image = model.render(cam, config.train.raster, background=background, camera_index=scene.camera_index(cam))
            save_png(out.renders / png_name(cam.name), image["image"].clamp(0, 1))
    print(f"wrote {len(cams)} renders to {out.renders}")
    return 0


def cmd_eval(args) -> int:
    device = resolve_device(args.device)
    model, config, run = load_run(args.run, device)
    metrics = evaluate_model(model, config.scene.load(), config, run, device)
    run.write_json(run.path / "eval.json", metrics)
    print_metrics(metrics)
    return 0


def cmd_export(args) -> int:
    device = resolve_device(args.device)
    model, config, run = load_run(args.run, device)
    out = args.out or str(run.path / "export_3dgs.ply")
    if isinstance(model, GaussianModel):  # already 3DGS: its own file, with every SH coefficient
        model.save_ply(out)
        print(f"wrote {model.num_gaussians} Gaussians (SH degree {model.sh_degree}) to {out}")
        return 0
    cams = config.scene.load().train
    if not 0 <= args.view < len(cams):
        raise CommandError(f"--view must be in [0, {len(cams)})")
    g = model.gaussians(cams[args.view], camera_index=args.view)
    export_3dgs_ply(out, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"])
    print(f"wrote {g['means'].shape[0]} Gaussians of all {model.anchors.num_anchors} anchors (decoded with the view "
          f"directions of training view {cams[args.view].name}) to {out}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("train", help="train a Scaffold-GS model (or plain 3DGS with --model 3dgs)")
    add_config_flags(p, SCENE_FLAGS + TRAIN_FLAGS + MODEL_FLAGS + HEAD_FLAGS, TRAIN_DEFAULTS)
    add_run_arguments(p, default_out="runs/scaffold")
    p.set_defaults(func=cmd_train)

    for name, func, helptext in (("render", cmd_render, "render a trained run's views to PNG"),
                                 ("eval", cmd_eval, "held-out metrics of a trained run"),
                                 ("export", cmd_export, "write the decoded Gaussians as a standard 3DGS PLY")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("run", help="run folder written by `securegs train` or `securegs hide`")
        p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
        if name == "render":
            p.add_argument("--split", choices=("test", "train"), default="test", help="which views (default: test)")
            p.add_argument("--out", help="folder for renders/ (default: the run folder)")
        if name == "export":
            p.add_argument("--view", type=int, default=0,
                           help="training view whose view directions decode every anchor (Scaffold-GS's colours "
                                "and opacities depend on the view; default 0)")
            p.add_argument("--out", help="PLY path (default RUN/export_3dgs.ply)")
        p.set_defaults(func=func)
