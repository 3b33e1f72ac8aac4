"""What every ``securegs`` command shares: options that parse into the config tree, the device,
run folders, the training loop with its checkpoints, and printing metrics."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import sys

import torch

from ..config import (RESUMABLE_CHANGES, RunConfig, SecureConfig, apply_overrides, field_paths, first_difference,
                      from_dict, resolve_field, to_dict)
from ..rasterizer import RasterOptions
from ..runs import RunFolder
from ..train.base import psnr_label


class CommandError(ValueError):
    """A command cannot go on; the message says why and what to do (printed as ``error: ...``)."""


def resolve_device(name: str | None) -> torch.device:
    """``name`` as a torch device this torch can use (default: CUDA when present, else the CPU).
    On the CPU, torch gets half the cores (see ``cpu_threads``)."""
    device = _device(name)
    if device.type == "cpu":
        torch.set_num_threads(cpu_threads())
    return device


def cpu_threads() -> int:
    """Torch's thread count for CPU training: half the cores (at least one). The MLPs are small and
    Warp's CPU kernels run on one thread, so more threads gain little alone, while two runs that each
    take every core oversubscribe the machine and slow each other down many times over."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 2)
    return max(1, cores // 2)


def _device(name: str | None) -> torch.device:
    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise CommandError(f"--device {name!r} is not a device name (use cpu or cuda[:N])") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise CommandError(f"--device {name}: only cpu and cuda are supported")
    if not torch.cuda.is_available():
        raise CommandError(f"--device {name}: this torch build has no usable CUDA device; use --device cpu")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise CommandError(f"--device {name}: there are only {torch.cuda.device_count()} CUDA device(s)")
    return device


def quiet_warp() -> None:
    """Warp without its banner and module-load lines (they would interleave with the progress bar).

    Where torch sees no CUDA device, Warp's native library still looks for the CUDA driver when it
    loads and prints a warning from C to file descriptor 2 on every command; that one line is
    silenced by pointing descriptor 2 at /dev/null while Warp initialises."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp >= 1.19 (the project's minimum): `quiet` is gone
    if torch.cuda.is_available():
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


# ---------------------------------------------------------------------------------------------
# Options that are config fields: each flag names the field it sets; type and default come from it
# ---------------------------------------------------------------------------------------------

# (flag, config field, help). Values are parsed by the config tree, so a bad one is refused with
# the field's own message; a flag left out keeps the config's default.
SCENE_FLAGS = (
    ("--scene", "scene.source", "built-in scene (synthetic, room, garden) or a COLMAP / NeRF-synthetic folder"),
    ("--width", "scene.width", "synthetic scenes: image width in pixels"),
    ("--height", "scene.height", "synthetic scenes: image height in pixels"),
    ("--train-views", "scene.n_train", "synthetic scenes: training views"),
    ("--test-views", "scene.n_test", "synthetic scenes: held-out views (metrics are computed on them)"),
    ("--downscale", "scene.downscale", "real data: image downscale factor"),
)
TRAIN_FLAGS = (
    ("--iterations", "train.iterations", "training steps"),
    ("--seed", "train.seed", "random seed of the training (initialisation, view order, growth draws); the synthetic "
                             "scene's layout has its own, --set scene.seed=N"),
    ("--tile-size", "train.raster.tile_size", "rasterizer tile: 8, 16 or 32 (default: 8 on the CPU, 16 on CUDA)"),
)
HEAD_FLAGS = (
    ("--feat-bank", "train.heads.feature_bank", "Scaffold-GS feature bank"),
    ("--appearance-dim", "train.heads.appearance_dim", "per-camera appearance embedding of this width (0: none)"),
)


def add_config_flags(parser: argparse.ArgumentParser, flags, defaults: dict | None = None) -> None:
    """One argparse option per (flag, field, help); ``defaults`` {field: value} overrides the
    config's default in the help text and when the flag is left out."""
    types = field_paths(RunConfig(secure=SecureConfig()))
    for flag, field, helptext in flags:
        default = (defaults or {}).get(field, _default_of(field))
        if types[field] is bool:
            parser.add_argument(flag, dest=field, action="store_const", const=True, default=None, help=helptext)
        else:
            # A help text that states its own default (one that depends on the device) keeps it.
            shown = helptext if "(default:" in helptext else f"{helptext} (default: {default})"
            parser.add_argument(flag, dest=field, default=None, metavar=field.rsplit(".", 1)[-1].upper(), help=shown)


def _default_of(field: str):
    value = RunConfig(secure=SecureConfig())
    for part in field.split("."):
        value = getattr(value, part)
    return value


def given_fields(args, base: RunConfig) -> dict:
    """Dotted field -> value of every config flag the user gave and every ``--set FIELD=VALUE``
    (the flags win over ``--set`` on the same field)."""
    given = {name: value for name, value in vars(args).items() if "." in name and value is not None}
    settings = {}
    for setting in getattr(args, "settings", None) or []:
        name, sep, value = setting.partition("=")
        if not sep or not name or not value:
            raise CommandError(f"--set {setting!r}: expected FIELD=VALUE")
        settings[resolve_field(base, name)] = value
    return {**settings, **given}


def config_from_args(args, base: RunConfig, defaults: dict | None = None, device=None) -> RunConfig:
    """``base`` with the command's defaults and ``given_fields`` applied; the rasterizer tile
    follows the device unless ``--tile-size`` was given."""
    given = given_fields(args, base)
    config = apply_overrides(base, {**(defaults or {}), **given})
    if "train.raster.tile_size" not in given and device is not None:
        config = apply_overrides(config, {"train.raster.tile_size": RasterOptions.for_device(device).tile_size})
    return config


def add_run_arguments(p: argparse.ArgumentParser, default_out: str) -> None:
    """Options of a command that trains into a run folder."""
    p.add_argument("--out", default=default_out, help=f"run folder to write (default: {default_out})")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--force", action="store_true",
                   help="start over in --out, replacing the files an earlier run wrote there (nothing else)")
    p.add_argument("--log-every", type=int, default=50, help="steps between lines of log.jsonl (default: 50)")
    p.add_argument("--checkpoint-every", type=int, default=200,
                   help="steps between checkpoints (default: 200); one is also written at the end and on Ctrl-C")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="FIELD=VALUE",
                   help="any other config field by its dotted path or a unique tail of it, e.g. "
                        "--set train.mlp_offset_lr=0.0012,0.00012 (repeatable; config.json lists the fields)")


def check_run_arguments(args) -> None:
    for name in ("log_every", "checkpoint_every"):
        if getattr(args, name) < 1:
            raise CommandError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")


# ---------------------------------------------------------------------------------------------
# Run folders and the training loop
# ---------------------------------------------------------------------------------------------


def prepare_run(run: RunFolder, config: RunConfig, args) -> bool:
    """Decide whether to resume (True) or start afresh (False); refuse to mix runs or to touch a
    folder that is not one of ours. Nothing is removed here: ``start_training`` clears an earlier
    run (``--force``) once the new run's scene and trainer exist, so that a wrong input leaves it."""
    if run.path.exists() and not run.path.is_dir():
        raise CommandError(f"--out {run.path} is a file, not a folder")
    if args.resume and run.checkpoint.is_file():
        saved = from_dict(RunConfig, run.read_config())
        field = first_difference(config, saved, ignore=RESUMABLE_CHANGES)
        if field is not None:
            raise CommandError(f"{run.config}: the run was made with another {field} "
                               f"({_lookup(saved, field)!r}, now {_lookup(config, field)!r}); resume with the same "
                               "options")
        return True
    if args.resume and run.config.is_file() and not args.force:
        raise CommandError(f"{run.path} holds a run but no checkpoint to resume from (it stopped before its first "
                           "checkpoint, or it finished and its checkpoint was removed); add --force to start over")
    if run.config.is_file() and not args.force:
        raise CommandError(f"{run.path} already holds a run; add --resume to continue it or --force to start over")
    if not run.config.is_file() and run.path.is_dir() and any(run.path.iterdir()):
        raise CommandError(f"--out {run.path} is a folder with other files in it (not a securegs run); "
                           "choose a new or empty folder")
    return False


def _lookup(config, field: str):
    for part in field.split("."):
        config = getattr(config, part, None)
    return to_dict(config) if dataclasses.is_dataclass(config) else config


def start_training(trainer, run: RunFolder, config: RunConfig, resume: bool, args, finish,
                   passphrase: str | None = None) -> int:
    """Resume or start (clearing an earlier run's files, which ``prepare_run`` allowed), record the
    config, and train; ``passphrase`` seals every checkpoint."""
    if resume:
        trainer.load_checkpoint(run.checkpoint, passphrase)
        print(f"resuming {run.path} at step {trainer.step_count}")
    else:
        run.clear()
    run.write_json(run.config, to_dict(config))
    return train_loop(trainer, run, args, finish, passphrase)


@contextlib.contextmanager
def _interrupt_between_steps():
    """Ctrl-C (SIGINT) and SIGTERM set a flag instead of stopping a step half-way; the loop checks
    it between steps, so the checkpoint it then writes is of a whole step."""
    stop = {"signal": None}

    def handler(signum, _frame):
        stop["signal"] = signum

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


# A step that reports one of these is always logged: densification changed the model (Scaffold-GS's
# grown anchors, 3DGS's clones and opacity resets), or the update was skipped.
CHANGE_KEYS = ("grown", "cloned", "opacity_reset", "nonfinite_grads", "incomplete_renders")


def train_loop(trainer, run: RunFolder, args, finish, passphrase: str | None = None) -> int:
    """Step the trainer to its ``total_steps`` with a progress bar, logs and checkpoints."""
    from tqdm import tqdm

    total = trainer.total_steps
    bar = tqdm(total=total, initial=trainer.step_count, desc="train", unit="step", dynamic_ncols=True,
               disable=args.quiet)
    with _interrupt_between_steps() as stop:
        while trainer.step_count < total:
            try:
                stats = trainer.step()
            except KeyboardInterrupt:  # raised inside a step: the trainer is still at the last whole step
                stop["signal"], stats = signal.SIGINT, None
            if stats is None:
                bar.close()
                return _interrupted(trainer, run, passphrase)
            bar.update(1)
            bar.set_postfix(loss=f"{stats['loss']:.4f}", **{psnr_label(stats): f"{stats['psnr']:.2f}"},
                            **{k: stats[k] for k in ("anchors", "gaussians") if k in stats})
            step = trainer.step_count
            if step % args.log_every == 0 or step == total or any(k in stats for k in CHANGE_KEYS):
                run.append_log({"step": step, "seconds": round(trainer.train_seconds, 2), **stats})
            if step % args.checkpoint_every == 0:
                trainer.save_checkpoint(run.checkpoint, passphrase)
            if stop["signal"] is not None:
                bar.close()
                return _interrupted(trainer, run, passphrase)
    bar.close()
    trainer.save_checkpoint(run.checkpoint, passphrase)
    finish()
    return 0


def _interrupted(trainer, run: RunFolder, passphrase: str | None) -> int:
    trainer.save_checkpoint(run.checkpoint, passphrase)
    print(f"\ninterrupted at step {trainer.step_count}; checkpoint saved. Continue with the same command and "
          "--resume.", file=sys.stderr)
    return 130


def print_metrics(metrics: dict) -> None:
    keys = ("psnr", "ssim", "lpips", "fps", "size_mb", "psnr_public", "ssim_public", "psnr_hidden", "ssim_hidden",
            "bit_accuracy", "fps_public", "fps_hidden", "size_mb_public", "anchors", "gaussians", "train_seconds")
    # A release with several secrets reports each one's hidden metrics with its suffix (_2, _3 ...).
    keys = [name for k in keys for name in [k] + sorted(m for m in metrics if m.rpartition("_")[0] == k
                                                           and m.rpartition("_")[2].isdigit())]
    print("  ".join(f"{k}={metrics[k]:.4g}" if isinstance(metrics.get(k), float) else f"{k}={metrics.get(k)}"
                    for k in keys if k in metrics))
    if metrics.get("lpips_note"):
        print(metrics["lpips_note"])

