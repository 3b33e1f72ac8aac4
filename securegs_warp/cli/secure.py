"""``securegs hide``, ``reveal`` and ``demo``: make a container, open it with or without the key."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import sys

import numpy as np
import torch

from ..config import RunConfig, SecureConfig, to_dict
from ..data import Camera
from ..io import export_3dgs_ply
from ..runs import RunFolder, png_name, save_png
from ..keys import is_sealed
from ..secure.container import KeyViews, open_container, save_container
from ..secure.payload import PayloadSpec
from ..secure.security import exposure
from . import common
from .common import CommandError
from .train import evaluate_model

HIDE_DEFAULTS = {"train.iterations": 400}
SECURE_FLAGS = (
    ("--payload", "secure.payload", "what to hide: object | scene | image[:FILE[@VIEW]] | bits[:L or :0101...], "
                                    "joined with +"),
    ("--hide", "scene.hidden", "synthetic scenes: the hidden object (mug, lamp, pawn, robot, a mesh file) or hidden "
                               "scene (scene, garden, room); default mug / scene"),
    ("--level", "scene.level", "hidden object alone on a background (object) or inside the scene (scene)"),
    ("--placement", "scene.hidden_placement", "synthetic scenes: the hidden object stands on the central object "
                                              "(stand), sinks half into it (sink) or floats above it (float)"),
    ("--hidden-position", "scene.hidden_position", "synthetic scenes: x,y,z of the hidden object's bottom centre "
                                                   "(world units; the room is 10 wide); replaces --placement"),
    ("--hidden-size", "scene.hidden_size", "synthetic scenes: the hidden object's largest side (world units)"),
    ("--hidden-yaw", "scene.hidden_yaw", "synthetic scenes: the hidden object's turn about the vertical, degrees"),
    ("--mode", "secure.strategy.mode", "density strategy: rdo (the paper's), cover (the cover's own anchors "
                                       "decode the hidden object: no anchor grows for it), or the ablations "
                                       "scaffold, global, shared"),
    ("--hidden-frame", "secure.hidden_frame", "where the private heads place hidden Gaussians: anchor (near their "
                                              "anchor, the paper's) or box (anywhere in the object's box); default "
                                              "box with --mode cover, anchor otherwise"),
    ("--hidden-offsets", "secure.hidden_offsets", "hidden Gaussians per anchor k_hid (default: 32 in the box frame, "
                                                  "the public 10 otherwise)"),
    ("--hidden-width", "secure.hidden_width", "hidden width of the private MLPs (default: 128 in the box frame, "
                                              "32 otherwise)"),
    ("--hidden-anchors", "secure.hidden_anchors", "box frame: how many anchors nearest the object decode it "
                                                  "(default 1024)"),
    ("--hidden-weight", "secure.hidden_weight", "λ of ℓ_ori + λ·ℓ_hid (None: the paper's 10 for objects, 0.1 for an "
                                                "image, 1 for a scene); lower keeps the cover closer to plain "
                                                "Scaffold-GS"),
    ("--hidden-feature-grad", "secure.hidden_feature_grad",
     "share of the hidden loss's gradient reaching the public anchor features, 0 to 1 (lower: the cover stays "
     "closer to plain Scaffold-GS; the paper's 1)"),
    ("--bit-margin", "secure.bit_margin", "logit margin by which every anchor's vote must agree with its bit (the "
                                          "bits live in the public anchor features: higher costs the cover)"),
    ("--r-down", "secure.strategy.r_down", "RDO: the public growth threshold is divided by this inside the hidden "
                                          "object's box (everywhere with --mode global)"),
    ("--hidden-every", "secure.strategy.hidden_every", "RDO: accumulate ∇_hid every N steps (larger grows fewer "
                                                       "hidden-only anchors)"),
    ("--robust", "secure.robust", "attacks the hidden payload trains against, joined with + (prune-random:F, "
                                  "noise-xyz:S, noise-feat:S, quantize:B; strengths drawn each step up to these); the "
                                  "cover's render is untouched"),
    ("--hidden-tau-scale", "secure.strategy.hidden_tau_scale",
     "RDO: anchors serving only the hidden payload grow at τ_fix times this (larger shows less of a hidden "
     "object's shape in the release and renders it less well)"),
)


def passphrase_from(args) -> str | None:
    """The passphrase from the environment variable named by --passphrase-env (never from argv,
    where other users of the machine could read it)."""
    if not args.passphrase_env:
        return None
    value = os.environ.get(args.passphrase_env)
    if not value:
        raise CommandError(f"--passphrase-env {args.passphrase_env}: that environment variable is empty or unset")
    return value


def hide_config(args, device) -> RunConfig:
    """The run's config from the command line; the payload is checked against the scene here."""
    config = common.config_from_args(args, RunConfig(secure=SecureConfig()), HIDE_DEFAULTS, device)
    spec = PayloadSpec.parse(config.secure.payload)
    scene = config.scene
    if spec.kind in ("object", "scene"):
        if not scene.builtin:
            raise CommandError(f"payload {spec.kind!r} needs hidden views, which only the built-in scenes render; "
                               "on real data hide an image or bits")
        if scene.hidden is None:
            scene = dataclasses.replace(scene, hidden="mug" if spec.kind == "object" else "scene")
    elif scene.hidden is not None:
        raise CommandError(f"--hide {scene.hidden}: payload {config.secure.payload!r} hides no object or scene")
    return dataclasses.replace(config, scene=scene)


def cmd_hide(args) -> int:
    from ..secure import SecureTrainer

    common.check_run_arguments(args)
    device = common.resolve_device(args.device)
    config = hide_config(args, device)
    passphrase = passphrase_from(args)  # fail before training, not after
    common.quiet_warp()
    run = RunFolder(args.out)
    with private_files():
        record = recorded(config)
        resume = common.prepare_run(run, record, args)
        if resume and passphrase is None and is_sealed(run.checkpoint.read_bytes()[:64]):
            raise CommandError(f"{run.path} is a sealed run (its key and checkpoints are sealed): resume it with "
                               "--passphrase-env VAR")
        run.path.mkdir(parents=True, exist_ok=True)
        os.chmod(run.path, 0o700)
        trainer = SecureTrainer(config.scene.load(), config.train, config.secure, device=device)
        return common.start_training(trainer, run, record, resume, args,
                              finish=lambda: finish_container(trainer, run, config, passphrase), passphrase=passphrase)


def recorded(config: RunConfig) -> RunConfig:
    """What config.json records: the config with a literal bit message replaced by its length
    (``bits:0b1011`` -> ``bits:4``). The message itself is kept only in the key and the
    checkpoints, which a sealed run seals; resuming takes it from the checkpoint."""
    payload = PayloadSpec.parse(config.secure.payload).describe()
    return dataclasses.replace(config, secure=dataclasses.replace(config.secure, payload=payload))


@contextlib.contextmanager
def private_files():
    """Files and folders created meanwhile are its owner's only (umask 077): a SecureGS run folder
    holds the private heads (checkpoints), scores of the hidden payload and renders of it."""
    previous = os.umask(0o077)
    try:
        yield
    finally:
        os.umask(previous)


def key_metadata(trainer) -> dict:
    """What the key stores besides the private heads: everything ``reveal`` needs to render the
    hidden payload (the cameras, which of them show it, the backgrounds, the rasterizer options)."""
    p, scene = trainer.payload, trainer.scene
    if p.image_view is not None:
        cams = [scene.train[p.image_view]]
    else:
        cams = scene.test or scene.train
    return {"payload": p.spec.describe(), "raster": to_dict(trainer.config.raster),
            "background": None if scene.background is None else [float(v) for v in scene.background],
            "hidden_background": p.background.tolist(), "cameras": [c.to_record() for c in cams],
            "hidden_views": [c.name for c in cams] if p.has_images else [],
            "image_view": p.image_view}


def finish_container(trainer, run: RunFolder, config: RunConfig, passphrase: str | None) -> dict:
    """Write release + key, the three demo renders and metrics.json; returns the metrics."""
    p = trainer.payload
    public, key = save_container(run.path, trainer.model, key_metadata(trainer), passphrase)
    public_metrics = evaluate_model(trainer.model, trainer.scene, config, run, trainer.device)
    metrics = {f"{k}_public" if k in ("psnr", "ssim", "lpips", "fps", "size_mb") else k: v
               for k, v in public_metrics.items()}
    metrics.update(trainer.evaluate_hidden())
    metrics.update(key_file=key.name, anchors=trainer.model.anchors.num_anchors,
                   train_seconds=round(trainer.train_seconds, 2), payload=p.spec.describe(),
                   mode=trainer.strategy.mode, hidden_anchors=int(trainer.strategy_state["is_hidden"].sum()))
    scene = trainer.scene
    if scene.hidden_points is not None:
        radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
        metrics["exposure"] = exposure(trainer.model.anchors.xyz.detach().cpu().numpy(), scene.hidden_points,
                                       scene.points, radius)
    write_demo_renders(trainer, run)
    run.write_json(run.metrics, metrics)
    common.print_metrics(metrics)
    if metrics.get("hidden_learnt") is False:
        print(f"warning: the hidden payload was not learnt: its render ({metrics['psnr_hidden']:.2f} dB) is not "
              f"1 dB better than a flat image of each target's mean colour ({metrics['psnr_hidden_flat']:.2f} dB). "
              "Train longer (--iterations) or let more of the hidden loss reach the anchor features "
              "(--hidden-feature-grad).", file=sys.stderr)
    return metrics


@torch.no_grad()
def write_demo_renders(trainer, run: RunFolder) -> None:
    """The public view, the hidden view with the key, and the same view without the key."""
    p = trainer.payload
    view = p.image_view if p.image_view is not None else 0
    cams = trainer.scene.train if p.image_view is not None else (trainer.scene.test or trainer.scene.train)
    cam = cams[view]
    public = trainer.render(cam)["image"].clamp(0, 1)
    save_png(run.renders / "public_view.png", public)
    save_png(run.renders / "hidden_view_without_key.png", public)  # all a keyless viewer can get
    if trainer.model.renders_hidden:
        save_png(run.renders / "hidden_view_with_key.png", trainer.render_hidden(cam, view)["image"].clamp(0, 1))


@torch.no_grad()
def cmd_reveal(args) -> int:
    device = common.resolve_device(args.device)
    common.quiet_warp()
    model, meta = open_container(args.release, args.key, passphrase_from(args), device=device)
    out = RunFolder(args.out)
    prepare_reveal_folder(out, args.force)
    if model.private is None:
        if getattr(args, "scene.source") is None:
            raise CommandError("without --key, reveal renders the cover scene only and needs --scene for its cameras "
                               "(the release itself stores none)")
        cams = args_scene_cameras(args)
        for cam in cams:
            save_png(out.renders / png_name(cam.name, "public_"), model.render(cam)["image"].clamp(0, 1))
        print(f"no key: rendered the cover scene only ({len(cams)} views in {out.renders})")
        return 0
    views = KeyViews.from_metadata(meta, device)
    for cam in views.cameras:
        save_png(out.renders / png_name(cam.name, "public_"),
                 model.render(cam, views.raster, background=views.background)["image"].clamp(0, 1))
    if model.private.bits is not None:
        bits = model.decode_bits()
        print("bits:", "".join(str(int(b)) for b in bits))
        out.write_json(out.path / "bits.json", {"bits": bits.tolist()})
    if model.renders_hidden:
        hidden_cams = views.hidden
        for cam in hidden_cams:
            r = model.render_hidden(cam, views.raster, background=views.hidden_background)
            save_png(out.renders / png_name(cam.name, "hidden_"), r["image"].clamp(0, 1))
        g = model.hidden_gaussians(hidden_cams[0])
        ply = out.path / "hidden_3dgs.ply"
        export_3dgs_ply(ply, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"])
        print(f"hidden views in {out.renders}; hidden Gaussians of every anchor ({g['means'].shape[0]}, decoded "
              f"with the view directions of {hidden_cams[0].name}) in {ply}")
    return 0


REVEAL_FILES = ("bits.json", "hidden_3dgs.ply")


def prepare_reveal_folder(out: RunFolder, force: bool) -> None:
    """Refuse an --out that holds anything but an earlier reveal; replace that one only with --force."""
    path = out.path
    if path.exists() and not path.is_dir():
        raise CommandError(f"--out {path} is a file, not a folder")
    if not path.is_dir() or not any(path.iterdir()):
        return
    ours = [path / name for name in REVEAL_FILES] + [out.renders]
    renders_ours = not out.renders.exists() or all(
        p.suffix == ".png" and p.name.startswith(("public_", "hidden_")) for p in out.renders.iterdir())
    others = sorted(p.name for p in path.iterdir() if p not in ours)
    if others or not renders_ours:
        raise CommandError(f"--out {path} holds other files ({', '.join(others) or 'renders/ of something else'}); "
                           "choose a new or empty folder")
    if not force:
        raise CommandError(f"--out {path} holds an earlier reveal; add --force to replace it")
    for name in REVEAL_FILES:
        (path / name).unlink(missing_ok=True)
    shutil.rmtree(out.renders, ignore_errors=True)


def args_scene_cameras(args) -> list[Camera]:
    from ..config import SceneSpec, apply_overrides

    given = {name.split(".", 1)[1]: v for name, v in vars(args).items() if name.startswith("scene.") and v is not None}
    scene = apply_overrides(SceneSpec(), given).load()
    return scene.test or scene.train


def cmd_demo(args) -> int:
    from . import build_parser

    argv = ["hide", "--out", args.out, "--iterations", str(args.iterations)]
    argv += ["--quiet"] if args.quiet else []
    argv += ["--force"] if args.force else []
    argv += ["--device", args.device] if args.device else []
    return cmd_hide(build_parser().parse_args(argv))


def add_parsers(sub) -> None:
    p = sub.add_parser("hide", help="train a container hiding a payload; write the public release and the key")
    common.add_config_flags(p, common.SCENE_FLAGS + common.TRAIN_FLAGS + SECURE_FLAGS, HIDE_DEFAULTS)
    common.add_run_arguments(p, default_out="runs/secure")
    p.add_argument("--passphrase-env", help="seal the key with the passphrase in this environment variable")
    p.set_defaults(func=cmd_hide)

    p = sub.add_parser("reveal", help="open a release: with the key the hidden payload (the key holds the cameras), "
                                      "without it the cover scene from --scene's cameras")
    p.add_argument("release", help="the release folder (point_cloud.ply + MLPs)")
    p.add_argument("--key", help="the key file; without it only the cover scene renders")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--out", default="revealed", help="folder for the renders (default: revealed)")
    p.add_argument("--force", action="store_true", help="replace an earlier reveal in --out (nothing else)")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    common.add_config_flags(p, common.SCENE_FLAGS)
    p.set_defaults(func=cmd_reveal)

    p = sub.add_parser("demo", help="hide an object and 48 bits in the built-in scene; write release, key, "
                                    "renders and metrics.json")
    p.add_argument("--out", default="runs/demo", help="run folder (default: runs/demo)")
    p.add_argument("--iterations", type=int, default=HIDE_DEFAULTS["train.iterations"],
                   help=f"training steps (default: {HIDE_DEFAULTS['train.iterations']})")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true",
                   help="start over in --out, replacing the files an earlier run wrote there (nothing else)")
    p.set_defaults(func=cmd_demo)
