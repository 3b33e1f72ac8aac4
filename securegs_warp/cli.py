"""``securegs`` command line: train, render, eval, export (Scaffold-GS engine); hide, reveal, demo
(SecureGS, in cli_secure.py)."""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import torch

from .runs import RunFolder, SceneSpec, folder_size_mb, save_png


def _device(name: str | None) -> str:
    return name or ("cuda" if torch.cuda.is_available() else "cpu")


def _quiet_warp():
    import warp as wp

    wp.config.quiet = True
    wp.init()


def add_scene_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="synthetic",
                   help="built-in scene (synthetic, room, garden) or a COLMAP / NeRF-synthetic folder")
    p.add_argument("--width", type=int, default=128, help="synthetic scenes: image width")
    p.add_argument("--height", type=int, default=96, help="synthetic scenes: image height")
    p.add_argument("--train-views", type=int, default=32, help="synthetic scenes: training views")
    p.add_argument("--test-views", type=int, default=8, help="synthetic scenes: held-out views")
    p.add_argument("--downscale", type=int, default=1, help="real data: image downscale factor")
    p.add_argument("--seed", type=int, default=0)


def scene_spec(args) -> SceneSpec:
    return SceneSpec(source=args.scene, width=args.width, height=args.height, n_train=args.train_views,
                     n_test=args.test_views, seed=args.seed, downscale=args.downscale)


# ---------------------------------------------------------------------------------------------
# train


def cmd_train(args) -> int:
    from .io import save_scaffold
    from .train import ScaffoldTrainer, TrainConfig

    _quiet_warp()
    device = _device(args.device)
    run = RunFolder(args.out)
    config = TrainConfig(iterations=args.iterations, seed=args.seed,
                         tile_size=args.tile_size or (8 if device == "cpu" else 16),
                         use_feat_bank=args.feat_bank, appearance_dim=32 if args.appearance else 0)
    spec = scene_spec(args)
    record = {"scene": dataclasses.asdict(spec), "train": config.to_dict()}
    resume = prepare_run(run, record, args)
    trainer = ScaffoldTrainer(spec.load(), config, device=device)
    return start_training(trainer, run, record, resume, args,
                          finish=lambda: _finish_scaffold(trainer, run, save_scaffold))


class RunConflict(ValueError):
    """The output folder holds another run (or one made with other options)."""


def prepare_run(run: RunFolder, record: dict, args) -> bool:
    """Decide whether to resume (True) or start afresh (False); refuse to mix runs."""
    from .train import TrainConfig

    if args.resume and run.checkpoint.is_file():
        saved = run.read_config()
        same = ({k: v for k, v in saved.items() if k != "train"} == {k: v for k, v in record.items() if k != "train"}
                and TrainConfig.from_dict(saved["train"]).to_dict() == record["train"])
        if not same:
            raise RunConflict(f"{run.config} was written with other options; resume with the same command line")
        return True
    if run.config.is_file() and not args.force:
        raise RunConflict(f"{run.path} already holds a run; add --resume to continue it or --force to start over")
    for stale in (run.log, run.checkpoint, run.metrics):
        stale.unlink(missing_ok=True)
    return False


def start_training(trainer, run: RunFolder, record: dict, resume: bool, args, finish) -> int:
    if resume:
        trainer.load_checkpoint(run.checkpoint)
        print(f"resuming {run.path} at step {trainer.step_count}")
    run.write_json(run.config, record)
    return train_loop(trainer, run, args, finish)


def train_loop(trainer, run: RunFolder, args, finish) -> int:
    """Step the trainer to its iteration count with a progress bar, logs and checkpoints."""
    from tqdm import tqdm

    total = trainer.config.iterations
    bar = tqdm(total=total, initial=trainer.step_count, desc="train", unit="step", dynamic_ncols=True,
               disable=args.quiet)
    try:
        while trainer.step_count < total:
            stats = trainer.step()
            bar.update(1)
            bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", anchors=stats["anchors"])
            step = trainer.step_count
            if step % args.log_every == 0 or step == total or "grown" in stats or "nonfinite_grads" in stats:
                run.append_log({"step": step, "seconds": round(trainer.train_seconds, 2), **stats})
            if step % args.checkpoint_every == 0:
                trainer.save_checkpoint(run.checkpoint)
    except KeyboardInterrupt:
        bar.close()
        trainer.save_checkpoint(run.checkpoint)
        print(f"\ninterrupted at step {trainer.step_count}; checkpoint saved. Continue with the same command "
              "and --resume.", file=sys.stderr)
        return 130
    bar.close()
    trainer.save_checkpoint(run.checkpoint)
    finish()
    return 0


def _finish_scaffold(trainer, run: RunFolder, save_scaffold) -> None:
    save_scaffold(run.model, trainer.model, trainer.heads)
    metrics = evaluate_trainer(trainer, run)
    metrics.update(size_mb=round(folder_size_mb(run.model), 3), train_seconds=round(trainer.train_seconds, 2))
    run.write_json(run.metrics, metrics)
    _print_metrics(metrics)


def evaluate_trainer(trainer, run: RunFolder) -> dict:
    """Held-out metrics and FPS of the public render; writes the held-out renders as PNGs."""
    cams = trainer.scene.test or trainer.scene.train
    metrics = trainer.evaluate(cams, with_lpips=True,
                               on_render=lambda cam, image: save_png(run.renders / f"{cam.name}.png", image))
    return {**metrics, "device": str(trainer.device)}


def _print_metrics(metrics: dict) -> None:
    keys = ("psnr", "ssim", "lpips", "fps", "size_mb", "psnr_public", "ssim_public", "psnr_hidden", "ssim_hidden",
            "bit_accuracy", "fps_public", "fps_hidden", "size_mb_public", "anchors", "train_seconds")
    print("  ".join(f"{k}={metrics[k]:.4g}" if isinstance(metrics.get(k), float) else f"{k}={metrics.get(k)}"
                    for k in keys if k in metrics))
    if metrics.get("lpips_note"):
        print(metrics["lpips_note"])


# ---------------------------------------------------------------------------------------------
# render / eval / export: a trained run folder


def load_run(path, device):
    """(trainer with the saved model, run folder) for a finished run."""
    from .io import load_scaffold
    from .train import ScaffoldTrainer, TrainConfig

    _quiet_warp()
    run = RunFolder(path)
    saved = run.read_config()
    spec = SceneSpec(**saved["scene"])
    config = TrainConfig.from_dict(saved["train"])
    trainer = ScaffoldTrainer(spec.load(), config, device=device)
    trainer.model, trainer.heads = load_scaffold(run.model, device=device)
    return trainer, run


def cmd_render(args) -> int:
    trainer, run = load_run(args.run, _device(args.device))
    cams = trainer.scene.test if args.split == "test" else trainer.scene.train
    out = RunFolder(args.out) if args.out else run
    with torch.no_grad():
        for cam in cams:
            save_png(out.renders / f"{cam.name}.png", trainer.render(cam)["image"].clamp(0, 1))
    print(f"wrote {len(cams)} renders to {out.renders}")
    return 0


def cmd_eval(args) -> int:
    trainer, run = load_run(args.run, _device(args.device))
    metrics = evaluate_trainer(trainer, run)
    metrics["size_mb"] = round(folder_size_mb(run.model), 3)
    run.write_json(run.path / "eval.json", metrics)
    _print_metrics(metrics)
    return 0


def cmd_export(args) -> int:
    from .io import export_3dgs_ply

    trainer, run = load_run(args.run, _device(args.device))
    cams = trainer.scene.train
    if not 0 <= args.view < len(cams):
        print(f"error: --view must be in [0, {len(cams)})", file=sys.stderr)
        return 2
    with torch.no_grad():
        g = trainer.render(cams[args.view])["gaussians"]
    out = args.out or str(run.path / "export_3dgs.ply")
    export_3dgs_ply(out, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"])
    print(f"wrote {g['means'].shape[0]} Gaussians (decoded for view {cams[args.view].name}) to {out}")
    return 0


# ---------------------------------------------------------------------------------------------


def add_training_arguments(p: argparse.ArgumentParser, default_out: str, default_iterations: int) -> None:
    p.add_argument("--out", default=default_out, help="run folder")
    p.add_argument("--iterations", type=int, default=default_iterations)
    p.add_argument("--tile-size", type=int, choices=(8, 16, 32), help="default: 8 on the CPU, 16 on CUDA")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--force", action="store_true", help="overwrite an existing run in --out")
    p.add_argument("--log-every", type=int, default=50)
    p.add_argument("--checkpoint-every", type=int, default=200)
    p.add_argument("--device")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    from .cli_secure import add_secure_parsers

    parser = argparse.ArgumentParser(prog="securegs", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a Scaffold-GS model")
    add_scene_arguments(p)
    add_training_arguments(p, default_out="runs/scaffold", default_iterations=800)
    p.add_argument("--feat-bank", action="store_true", help="Scaffold-GS feature bank")
    p.add_argument("--appearance", action="store_true", help="per-camera appearance embedding")
    p.set_defaults(func=cmd_train)
    add_secure_parsers(sub, add_scene_arguments, add_training_arguments)

    for name, func, helptext in (("render", cmd_render, "render a trained run's views to PNG"),
                                 ("eval", cmd_eval, "held-out metrics of a trained run"),
                                 ("export", cmd_export, "write the decoded Gaussians as a standard 3DGS PLY")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("run", help="run folder written by `securegs train`")
        p.add_argument("--device")
        if name == "render":
            p.add_argument("--split", choices=("test", "train"), default="test")
            p.add_argument("--out", help="folder for renders/ (default: the run folder)")
        if name == "export":
            p.add_argument("--view", type=int, default=0, help="training view the Gaussians are decoded for")
            p.add_argument("--out", help="PLY path (default RUN/export_3dgs.ply)")
        p.set_defaults(func=func)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        code = args.func(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if code == 0 and not getattr(args, "quiet", False):
        print(f"done in {time.perf_counter() - t0:.1f} s")
    return code


if __name__ == "__main__":
    sys.exit(main())
