"""``securegs hide``, ``reveal`` and ``demo``: make a container, open it with or without the key."""
from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import torch

from .runs import RunFolder, SceneSpec, folder_size_mb, save_png

DEMO_PAYLOAD = "object+bits:48"
DEMO_ITERATIONS = 400


def _passphrase(args) -> str | None:
    """The passphrase from the environment variable named by --passphrase-env (never from argv,
    where other users of the machine could read it)."""
    if not args.passphrase_env:
        return None
    value = os.environ.get(args.passphrase_env)
    if not value:
        raise ValueError(f"--passphrase-env {args.passphrase_env}: that environment variable is empty or unset")
    return value


def cmd_hide(args) -> int:
    from .cli import _device, _quiet_warp, prepare_run, scene_spec, start_training
    from .secure import PayloadSpec, SecureTrainer
    from .train import TrainConfig

    _quiet_warp()
    device = _device(args.device)
    run = RunFolder(args.out)
    payload = PayloadSpec.parse(args.payload, seed=args.seed)
    spec = scene_spec(args)
    if spec.builtin and payload.kind in ("object", "scene"):
        spec.hidden = args.hide or ("mug" if payload.kind == "object" else "scene")
        spec.level = args.level
    config = TrainConfig(iterations=args.iterations, seed=args.seed,
                         tile_size=args.tile_size or (8 if device == "cpu" else 16))
    record = {"scene": dataclasses.asdict(spec), "train": config.to_dict(), "payload": payload.describe(),
              "mode": args.mode, "hidden_weight": args.hidden_weight, "r_down": args.r_down,
              "hidden_every": args.hidden_every, "hidden_tau_scale": args.hidden_tau_scale,
              "feature_grad": args.feature_grad}
    resume = prepare_run(run, record, args)
    passphrase = _passphrase(args)  # fail before training, not after
    trainer = SecureTrainer(spec.load(), config, payload, device=device, mode=args.mode,
                            hidden_weight=args.hidden_weight, hidden_feature_grad=args.feature_grad,
                            strategy_options={"r_down": args.r_down, "hidden_every": args.hidden_every,
                                              "hidden_tau_scale": args.hidden_tau_scale})
    return start_training(trainer, run, record, resume, args,
                          finish=lambda: finish_container(trainer, run, spec, passphrase))


def finish_container(trainer, run: RunFolder, spec: SceneSpec, passphrase: str | None) -> dict:
    """Write release + key, the three demo renders and metrics.json; returns the metrics."""
    from .cli import _print_metrics, evaluate_trainer
    from .secure.container import save_container
    from .secure.security import exposure

    p = trainer.payload
    metadata = {"payload": p.spec.describe(), "scene": dataclasses.asdict(spec),
                "hidden_background": p.background.tolist(), "image_view": p.image_view,
                "tile_size": trainer.config.tile_size}
    public, key = save_container(run.path, trainer.model, trainer.heads, trainer.private, metadata, passphrase)
    public_metrics = evaluate_trainer(trainer, run)
    metrics = {f"{k}_public" if k in ("psnr", "ssim", "lpips", "fps") else k: v for k, v in public_metrics.items()}
    metrics.update(trainer.evaluate_hidden())
    metrics.update(size_mb_public=round(folder_size_mb(public), 3), key_file=key.name,
                   train_seconds=round(trainer.train_seconds, 2), payload=p.spec.describe(),
                   mode=trainer.strategy.mode, hidden_anchors=int(trainer.strategy_state["is_hidden"].sum()))
    scene = trainer.scene
    if scene.hidden_points is not None:
        radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
        metrics["exposure"] = exposure(trainer.model.xyz.detach().cpu().numpy(), scene.hidden_points,
                                       scene.points, radius)
    write_demo_renders(trainer, run)
    run.write_json(run.metrics, metrics)
    _print_metrics(metrics)
    if metrics.get("hidden_learnt") is False:
        print(f"warning: the hidden payload was not learnt: its render ({metrics['psnr_hidden']:.2f} dB) is not "
              f"1 dB better than a flat image of each target's mean colour ({metrics['psnr_hidden_flat']:.2f} dB). "
              "Train longer (--iterations) or let more of the hidden loss reach the anchor features (--feature-grad).",
              file=sys.stderr)
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
    if trainer.private.decoder is not None:
        save_png(run.renders / "hidden_view_with_key.png", trainer.render_hidden(cam, view)["image"].clamp(0, 1))


@torch.no_grad()
def cmd_reveal(args) -> int:
    from .cli import _device, _quiet_warp, scene_spec
    from .io import export_3dgs_ply
    from .render import render_view
    from .secure.container import open_container

    _quiet_warp()
    device = _device(args.device)
    container = open_container(args.public, args.key, _passphrase(args), device=device)
    meta = container.metadata
    if args.scene is None and "scene" in meta:  # the key remembers the cameras it was made for
        spec = SceneSpec(**meta["scene"])
    else:
        args.scene = args.scene or "synthetic"
        spec = scene_spec(args)
    scene = spec.load()
    out = RunFolder(args.out)
    tile = dict(tile_size=meta.get("tile_size", 16))
    bg = torch.tensor(scene.background if scene.background is not None else (0, 0, 0), device=device,
                      dtype=torch.float32)
    cams = scene.test or scene.train
    for cam in cams:
        save_png(out.renders / f"public_{cam.name}.png",
                 render_view(container.model, container.heads, cam, bg, **tile)["image"].clamp(0, 1))
    if container.private is None:
        print(f"no key: rendered the cover scene only ({len(cams)} views in {out.renders})")
        return 0
    private = container.private
    if private.bit_mlp is not None:
        bits = private.decode_bits(container.model.feat)
        print("bits:", "".join(str(int(b)) for b in bits))
        out.write_json(out.path / "bits.json", {"bits": bits.tolist()})
    if private.decoder is not None:
        hidden_bg = torch.tensor(meta["hidden_background"], device=device, dtype=torch.float32)
        view = meta.get("image_view")
        hidden_cams = [scene.train[view]] if view is not None else cams
        for cam in hidden_cams:
            r = render_view(container.model, private.decoder, cam, hidden_bg, offset_source=private.hidden_offsets,
                            **tile)
            save_png(out.renders / f"hidden_{cam.name}.png", r["image"].clamp(0, 1))
        g = r["gaussians"]
        ply = out.path / "hidden_3dgs.ply"
        export_3dgs_ply(ply, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"])
        print(f"hidden views in {out.renders}; hidden Gaussians ({g['means'].shape[0]}) in {ply}")
    return 0


def cmd_demo(args) -> int:
    from .cli import build_parser

    argv = ["hide", "--out", args.out, "--payload", DEMO_PAYLOAD, "--iterations", str(args.iterations), "--force"]
    argv += ["--quiet"] if args.quiet else []
    argv += ["--device", args.device] if args.device else []
    return cmd_hide(build_parser().parse_args(argv))


def add_secure_parsers(sub, add_scene_arguments, add_training_arguments) -> None:
    from .secure import HIDDEN_FEATURE_GRAD, MODES

    p = sub.add_parser("hide", help="train a container hiding a payload; write the public release and the key")
    add_scene_arguments(p)
    add_training_arguments(p, default_out="runs/secure", default_iterations=DEMO_ITERATIONS)
    p.add_argument("--payload", default=DEMO_PAYLOAD,
                   help="object | scene | image[:FILE[@VIEW]] | bits[:L or :0101...], joined with +")
    p.add_argument("--hide", help="synthetic scenes: the hidden object (mug, lamp, pawn, robot, a mesh file) "
                                  "or hidden scene (scene, garden, room)")
    p.add_argument("--level", choices=("object", "scene"), default="object",
                   help="hidden object alone on a background (object) or inside the scene (scene)")
    p.add_argument("--mode", choices=MODES, default="rdo", help="density strategy (ablations: scaffold, global, shared)")
    p.add_argument("--hidden-weight", type=float, metavar="LAMBDA",
                   help="λ of ℓ_ori + λ·ℓ_hid (default: the paper's 10 for objects, 0.1 for an image, 1 for a "
                        "scene); lower keeps the cover scene closer to a plain Scaffold-GS model")
    p.add_argument("--r-down", type=float, default=4.0,
                   help="RDO: the public growth threshold is divided by this inside the hidden object's box "
                        "(more public anchors there mask the hidden ones; the paper's 4); everywhere with "
                        "--mode global")
    p.add_argument("--hidden-every", type=int, default=2,
                   help="RDO: accumulate ∇_hid every N steps (larger grows fewer hidden-only anchors)")
    p.add_argument("--hidden-tau-scale", type=float, default=1.0,
                   help="RDO: anchors serving only the hidden payload grow at τ_fix times this (the paper's 1; "
                        "larger shows less of a hidden object's shape in the release and renders it less well)")
    p.add_argument("--feature-grad", type=float, default=HIDDEN_FEATURE_GRAD,
                   help="share of the hidden loss's gradient reaching the public anchor features, 0 to 1 "
                        f"(default {HIDDEN_FEATURE_GRAD}: the cover stays closer to plain Scaffold-GS; the paper's 1)")
    p.add_argument("--passphrase-env", help="seal the key with the passphrase in this environment variable")
    p.set_defaults(func=cmd_hide)

    p = sub.add_parser("reveal", help="open a release: the cover scene, and with the key the hidden payload")
    p.add_argument("public", help="the release folder (point_cloud.ply + MLPs)")
    p.add_argument("--key", help="the key file; without it only the cover scene renders")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--out", default="revealed")
    p.add_argument("--device")
    add_scene_arguments(p)
    p.set_defaults(func=cmd_reveal, scene=None)

    p = sub.add_parser("demo", help="hide an object and 48 bits in the built-in scene; write release, key, "
                                    "renders and metrics.json")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--iterations", type=int, default=DEMO_ITERATIONS)
    p.add_argument("--device")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

