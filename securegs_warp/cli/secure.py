"""``securegs hide``, ``reveal`` and ``demo``: make a container, open it with or without a key.

``hide`` hides one secret, or several, each behind its own key: every ``--and`` starts another
secret with its own ``--payload``, ``--key-out`` and ``--passphrase-env``; the run's options (scene,
training, density strategy) come before the first ``--and`` and hold for all. The secrets are given
on the command line rather than in a file listing them because each needs only these three
options, which the command already has, and a run's config.json records their payloads anyway.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from ..config import (BOX_FRAME_DEFAULTS, FINISH_ROBUST_RECIPE, GRADIENT_SHARES, ROBUST_RECIPE, RunConfig, SecureConfig,
                      recorded_phase, to_dict)
from ..data import Camera
from ..io import export_3dgs_ply
from ..runs import RunFolder, png_name, save_png
from ..keys import is_sealed
from ..secure.container import PUBLIC_DIR, KeyFile, KeyViews, default_key_path, open_container, save_container
from ..secure.payload import SECRET_SEPARATOR, parse_secrets, recorded_payload
from ..secure.robust import ROBUST_SYNTAX
from ..secure.trainer import secret_suffix
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
    ("--hidden-up", "scene.hidden_up", "synthetic scenes: a mesh file's up axis, z (the default) or y (glTF, many "
                                       "OBJ exporters and scans)"),
    ("--mode", "secure.strategy.mode", "density strategy: cover (the cover's own anchors decode the hidden "
                                       "object: no anchor grows for it; the default when a secret hides an "
                                       "object, for every secret of the run, and for bits alone), rdo (the "
                                       "paper's; the default for images and scenes), or the ablations "
                                       "scaffold, global, shared"),
    ("--hidden-frame", "secure.hidden_frame", "where the private heads place hidden Gaussians: anchor (near their "
                                              "anchor, the paper's) or box (anywhere in the object's box); default "
                                              "box for an object in the cover mode, anchor otherwise"),
    ("--hidden-offsets", "secure.hidden_offsets", "hidden Gaussians per anchor k_hid (default: 32 in the box frame, "
                                                  "the public 10 otherwise)"),
    ("--hidden-width", "secure.hidden_width", "hidden width of the private MLPs (default: 128 in the box frame, "
                                              "32 otherwise)"),
    ("--hidden-anchors", "secure.hidden_anchors", "box frame: how many anchors nearest the object decode it "
                                                  "(default 1024)"),
    ("--hidden-encoding", "secure.hidden_encoding", "box frame: octaves of sines and cosines of the anchor's "
                                                    "position that F_o† reads (default 6; 0: the position alone)"),
    ("--hidden-latent", "secure.hidden_latent", "box frame: resolution of the key's private latent grid over the "
                                                "object's neighbourhood (default 0: none)"),
    ("--hidden-codes", "secure.hidden_codes", "box frame: rows of the key's private per-anchor codes, added to "
                                              f"the serving anchors' features (default {BOX_FRAME_DEFAULTS['codes']}; 0: none)"),
    ("--hidden-code-scales", "secure.hidden_code_scales", "box frame: the codes add to the serving anchors' "
                                                          "scalings too (needs the codes: not with --hidden-codes 0)"),
    ("--hidden-code-cells", "secure.hidden_code_cells", "box frame: the codes' cells per axis of the object's "
                                                        f"contracted neighbourhood, kept in the key (default: {BOX_FRAME_DEFAULTS['code_cells']})"),
    ("--hidden-depth", "secure.hidden_depth", "hidden layers of the private offset MLP F_o† (default 1)"),
    ("--hidden-eps2d", "secure.hidden_eps2d", "the hidden render's screen-space dilation, kept in the key (default: "
                                              "the public render's, 0.3)"),
    ("--hidden-scale-gain", "secure.hidden_scale_gain", "how many times its anchor's scale a hidden Gaussian may "
                                                        "grow, kept in the key (default 1; at low resolution larger "
                                                        "helps objects with large flat parts and costs others: "
                                                        "docs/results.md)"),
    ("--hidden-start", "secure.hidden_start", "box frame: where the hidden Gaussians start, surface (spread over "
                                              "the object's surface; the default) or centre (near the box's "
                                              "centre, as before)"),
    ("--hidden-stride", "secure.hidden_stride", "train the hidden branch on every N-th step only, its loss weighted "
                                                "N times (faster training, lower hidden fidelity; default 1)"),
    ("--hidden-finish", "secure.hidden_finish", "after the joint run, train the private heads alone for this "
                                                "fraction of --iterations more steps (the release does not "
                                                "change, only the key; 0: none; default 0.25 for an object in "
                                                "the cover mode, 0 otherwise); with --resume, a run that has "
                                                "not begun its phase takes this one"),
    ("--finish-robust", "secure.finish_robust", "attacks the finishing phase trains against, joined with + (as "
                                                f"--robust; none: none; auto: {FINISH_ROBUST_RECIPE} where "
                                                "--robust auto chose its recipe, --robust's attacks otherwise); with "
                                                "--resume, a run that has not begun its phase takes these"),
    ("--hidden-weight", "secure.hidden_weight", "λ of ℓ_ori + λ·ℓ_hid (None: the paper's 10 for objects, 0.1 for an "
                                                "image, 1 for a scene); lower keeps the cover closer to plain "
                                                "Scaffold-GS"),
    ("--hidden-feature-grad", "secure.hidden_feature_grad",
     "share of the hidden loss's gradient reaching the public anchor features, 0 to 1 (lower: the cover stays "
     f"closer to plain Scaffold-GS; the paper's 1; default 0 with private codes, {GRADIENT_SHARES[0]} otherwise)"),
    ("--hidden-scaling-grad", "secure.hidden_scaling_grad",
     "share of the hidden loss's gradient reaching the public anchor scalings, 0 to 1 (the paper's 1; default 0 "
     f"with private codes, {GRADIENT_SHARES[1]} otherwise)"),
    ("--bit-margin", "secure.bit_margin", "logit margin by which every anchor's vote must agree with its bit (the "
                                          "bits live in the public anchor features: higher costs the cover; None: "
                                          "0.25 with the automatic robust training, 1 otherwise)"),
    ("--bits-from", "secure.bits_from", "when the bits are projected into the anchor features: growth-end "
                                         "(once the density strategy has fixed the anchors, which are then "
                                         "plain Scaffold-GS's of the seed) or start (after every step)"),
    ("--bit-cell", "secure.bit_cell_voxels", "edge of the keyed grid cells that deal anchors among the bits, in "
                                             "voxels (larger: bits survive larger position changes; smaller: more "
                                             "independent voters per bit)"),
    ("--r-down", "secure.strategy.r_down", "RDO: the public growth threshold is divided by this inside the hidden "
                                          "object's box (everywhere with --mode global)"),
    ("--hidden-every", "secure.strategy.hidden_every", "RDO: accumulate ∇_hid every N steps (larger grows fewer "
                                                       "hidden-only anchors)"),
    ("--robust", "secure.robust", f"attacks the hidden payload trains against, joined with + ({ROBUST_SYNTAX}; "
                                  "strengths drawn each step up to these); the "
                                  "cover's render is untouched; none: no robust training; auto: "
                                  f"{ROBUST_RECIPE} for an object (and bits) in the cover mode, none "
                                  "otherwise"),
    ("--hidden-tau-scale", "secure.strategy.hidden_tau_scale",
     "RDO: anchors serving only the hidden payload grow at τ_fix times this (larger shows less of a hidden "
     "object's shape in the release and renders it less well)"),
)


def passphrase_from(args) -> str | None:
    """The passphrase from the environment variable named by --passphrase-env (never from argv,
    where other users of the machine could read it)."""
    return passphrase_from_env(args.passphrase_env)


def passphrase_from_env(name: str | None) -> str | None:
    """The value of environment variable ``name`` (None: no passphrase)."""
    if not name:
        return None
    value = os.environ.get(name)
    if not value:
        raise CommandError(f"--passphrase-env {name}: that environment variable is empty or unset")
    return value


@dataclasses.dataclass
class SecretOptions:
    """One secret's own options of ``hide``: its payload, where its key goes (None: OUT/key.safetensors
    or key.sealed; the first secret only) and its passphrase (None: a plain key)."""

    payload: str
    key_out: Path | None
    passphrase: str | None


def _secret_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="securegs hide ... --and", add_help=False, exit_on_error=False)
    p.add_argument("--payload")
    p.add_argument("--key-out")
    p.add_argument("--passphrase-env")
    return p


def secret_options(args) -> list[SecretOptions]:
    """Each secret's options: the first from before any ``--and``, one more per ``--and`` group.
    Refused: a group without --payload or --key-out, a run option inside a group, a --payload that
    names several secrets, two keys at one path, a key inside the release folder, an existing key
    file (unless --force or --resume), and sealed later keys beside plain checkpoints."""
    first = getattr(args, "secure.payload")
    secrets = [SecretOptions(first if first is not None else SecureConfig().payload,
                             None if args.key_out is None else Path(args.key_out), passphrase_from(args))]
    groups = []
    if args.more is not None:  # the words after the first --and, split at the others
        groups.append([])
        for word in args.more:
            if word == "--and":
                groups.append([])
            else:
                groups[-1].append(word)
    for group in groups:
        try:
            given, rest = _secret_parser().parse_known_args(group)
        except argparse.ArgumentError as e:
            raise CommandError(f"after --and: {e}") from None
        if rest:
            raise CommandError(f"after --and only a secret's own --payload, --key-out and --passphrase-env are read, "
                               f"not {rest[0]!r}: give the run's options before the first --and")
        if given.payload is None:
            raise CommandError("--and starts another secret: give its --payload (and --key-out) after it")
        if given.key_out is None:
            raise CommandError(f"the secret --payload {given.payload} (after --and) needs its own --key-out: where "
                               "its key is written")
        secrets.append(SecretOptions(given.payload, Path(given.key_out), passphrase_from_env(given.passphrase_env)))
    for secret in secrets:
        if SECRET_SEPARATOR in secret.payload:
            raise CommandError(f"--payload {secret.payload!r} names several secrets: give each further one after "
                               "--and with its own --key-out")
    _check_key_paths(args, secrets)
    if secrets[0].passphrase is None and any(s.passphrase for s in secrets[1:]):
        raise CommandError("a later secret's key is sealed but the first's is not: the run's checkpoints, which hold "
                           "every secret's heads, are sealed with the first secret's --passphrase-env; give it one")
    return secrets


def _check_key_paths(args, secrets: list[SecretOptions]) -> None:
    out = Path(args.out).resolve()
    first_default = default_key_path(out, secrets[0].passphrase)
    paths = [first_default if s.key_out is None else s.key_out.resolve() for s in secrets]
    for i, path in enumerate(paths):
        if path in paths[:i]:
            raise CommandError(f"--key-out {path}: two secrets' keys would be written to the same file")
        if path == out / PUBLIC_DIR or out / PUBLIC_DIR in path.parents:
            raise CommandError(f"--key-out {path} lies inside the release folder, which holds only what Scaffold-GS "
                               "reads; write keys elsewhere")
        if path.is_dir():
            raise CommandError(f"--key-out {path} is a folder; give a file name")
        if secrets[i].key_out is not None and path.exists() and not (args.force or args.resume):
            raise CommandError(f"--key-out {path} exists; add --force to replace it")


def hide_config(args, device, secrets: list[SecretOptions]) -> RunConfig:
    """The run's config from the command line and the secrets' payloads; the payloads are checked
    against the scene here."""
    base = RunConfig(secure=SecureConfig())
    config = common.config_from_args(args, base, HIDE_DEFAULTS, device)
    run = RunFolder(args.out)
    if args.resume and run.config.is_file():
        # A resumed run keeps its finishing phase's length and attacks unless the command asks for others.
        given = common.given_fields(args, base)
        kept = {name: value for name, value in recorded_phase(run.read_config().get("secure") or {}).items()
                if f"secure.{name}" not in given}
        config = dataclasses.replace(config, secure=dataclasses.replace(config.secure, **kept))
    payload = SECRET_SEPARATOR.join(s.payload for s in secrets)
    specs = parse_secrets(payload)
    config = dataclasses.replace(config, secure=dataclasses.replace(config.secure, payload=payload))
    scene = config.scene
    kinds = [spec.kind for spec in specs if spec.kind in ("object", "scene")]
    if kinds:
        if not scene.builtin:
            raise CommandError(f"payload {kinds[0]!r} needs hidden views, which only the built-in scenes render; "
                               "on real data hide an image or bits")
        if scene.hidden is None:
            scene = dataclasses.replace(scene, hidden="mug" if kinds[0] == "object" else "scene")
    elif scene.hidden is not None:
        raise CommandError(f"--hide {scene.hidden}: payload {payload!r} hides no object or scene")
    # config.json records the mode, the robust training, the bit margin and the finishing phase the
    # payload chose, so that a later default cannot change a resumed run.
    secret_kinds = [spec.kind for spec in specs]
    mode = config.secure.strategy_mode(secret_kinds)
    secure = dataclasses.replace(config.secure.resolved(secret_kinds, mode),
                                 strategy=dataclasses.replace(config.secure.strategy, mode=mode))
    return dataclasses.replace(config, scene=scene, secure=secure)


def cmd_hide(args) -> int:
    from ..secure import SecureTrainer

    common.check_run_arguments(args)
    device = common.resolve_device(args.device)
    secrets = secret_options(args)  # fail before training, not after
    config = hide_config(args, device, secrets)
    passphrase = secrets[0].passphrase  # seals the checkpoints too
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
        code = common.start_training(trainer, run, record, resume, args,
                                     finish=lambda: finish_container(trainer, run, config, secrets),
                                     passphrase=passphrase)
        if code == 0 and len({s.passphrase for s in secrets}) > 1:
            # The checkpoint holds every secret, sealed with the first secret's passphrase only: a
            # finished run needs none, so it does not stay behind for the holder of that passphrase.
            run.checkpoint.unlink(missing_ok=True)
        return code


def recorded(config: RunConfig) -> RunConfig:
    """What config.json records: the config with its payload as ``recorded_payload`` gives it
    (resuming takes the message from the checkpoint)."""
    return dataclasses.replace(config, secure=dataclasses.replace(config.secure,
                                                                  payload=recorded_payload(config.secure.payload)))


@contextlib.contextmanager
def private_files():
    """Files and folders created meanwhile are its owner's only (umask 077): a SecureGS run folder
    holds the private heads (checkpoints), scores of the hidden payload and renders of it."""
    previous = os.umask(0o077)
    try:
        yield
    finally:
        os.umask(previous)


def key_metadata(trainer, secret: int) -> dict:
    """What secret ``secret``'s key stores besides its private heads: everything ``reveal`` needs to
    render its hidden payload (the cameras, which of them show it, the backgrounds, the rasterizer
    options); nothing about the other secrets."""
    p, scene = trainer.payloads[secret], trainer.scene
    cams = hidden_cameras(trainer, p)
    return {"payload": p.spec.describe(), "raster": to_dict(trainer.config.raster),
            "background": None if scene.background is None else [float(v) for v in scene.background],
            "hidden_background": p.background.tolist(), "cameras": [c.to_record() for c in cams],
            "hidden_views": [c.name for c in cams] if p.has_images else [],
            "image_view": p.image_view}


def hidden_cameras(trainer, payload) -> list[Camera]:
    """The cameras a payload is revealed from: its image's view, or the held-out (else training) views."""
    scene = trainer.scene
    return [scene.train[payload.image_view]] if payload.image_view is not None else scene.evaluation_views


def finish_container(trainer, run: RunFolder, config: RunConfig, secrets: list[SecretOptions]) -> dict:
    """Write the release and a key per secret, the demo renders and metrics.json; returns the metrics.
    Each secret's hidden metrics, key file and payload carry its suffix (none for the first, _2 ...)."""
    keys = [KeyFile(key_metadata(trainer, i), s.key_out, s.passphrase) for i, s in enumerate(secrets)]
    public, paths = save_container(run.path, trainer.model, keys)
    public_metrics = evaluate_model(trainer.model, trainer.scene, config, run, trainer.device)
    metrics = {f"{k}_public" if k in ("psnr", "ssim", "lpips", "fps", "size_mb") else k: v
               for k, v in public_metrics.items()}
    for i, (p, path) in enumerate(zip(trainer.payloads, paths)):
        suffix = secret_suffix(i)
        metrics.update({k + suffix: v for k, v in trainer.evaluate_hidden(i).items()})
        metrics.update({"key_file" + suffix: path.name if path.parent == run.path else str(path),
                        "payload" + suffix: p.spec.describe()})
    metrics.update(anchors=trainer.model.anchors.num_anchors, train_seconds=round(trainer.train_seconds, 2),
                   mode=trainer.strategy.mode, robust=trainer.secure.robust, finish_robust=trainer.secure.finish_robust,
                   bit_margin=trainer.secure.bit_margin, hidden_anchors=int(trainer.strategy_state["is_hidden"].sum()))
    scene = trainer.scene
    if scene.hidden_points is not None:
        radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
        metrics["exposure"] = exposure(trainer.model.anchors.xyz.detach().cpu().numpy(), scene.hidden_points,
                                       scene.points, radius)
    write_demo_renders(trainer, run)
    run.write_json(run.metrics, metrics)
    common.print_metrics(metrics)
    for i in range(len(trainer.payloads)):
        suffix = secret_suffix(i)
        if metrics.get("hidden_learnt" + suffix) is False:
            print(f"warning: the hidden payload was not learnt ({metrics['payload' + suffix]}): its render "
                  f"({metrics['psnr_hidden' + suffix]:.2f} dB) is not 1 dB better than a flat image of each target's "
                  f"mean colour ({metrics['psnr_hidden_flat' + suffix]:.2f} dB). Train longer (--iterations) or let "
                  "more of the hidden loss reach the anchor features (--hidden-feature-grad).", file=sys.stderr)
    return metrics


@torch.no_grad()
def write_demo_renders(trainer, run: RunFolder) -> None:
    """The public view, each secret's hidden view with its key (hidden_view_with_key.png,
    hidden_view_with_key_2.png ...), and the first one's view without a key."""
    for i, p in enumerate(trainer.payloads):
        view = p.image_view if p.image_view is not None else 0
        cam = hidden_cameras(trainer, p)[0]
        if i == 0:
            public = trainer.render(cam)["image"].clamp(0, 1)
            save_png(run.renders / "public_view.png", public)
            save_png(run.renders / "hidden_view_without_key.png", public)  # all a keyless viewer can get
        if trainer.model.secrets[i].decoder is not None:
            save_png(run.renders / f"hidden_view_with_key{secret_suffix(i)}.png",
                     trainer.render_hidden(cam, view, secret=i)["image"].clamp(0, 1))


@torch.no_grad()
def cmd_reveal(args) -> int:
    device = common.resolve_device(args.device)
    common.quiet_warp()
    model, meta = open_container(args.release, args.key, passphrase_from(args), device=device)
    out = RunFolder(args.out)
    # Every input is read before an earlier reveal in --out is replaced: a wrong one leaves it.
    if model.private is None:
        if getattr(args, "scene.source") is None:
            raise CommandError("without --key, reveal renders the cover scene only and needs --scene for its cameras "
                               "(the release itself stores none)")
        cams = args_scene_cameras(args)
    else:
        views = KeyViews.from_metadata(meta, device)
    # What it writes (the message, the hidden renders and Gaussians) is the secret: its owner's only.
    with private_files():
        prepare_reveal_folder(out, args.force)
        if model.private is None:
            return _render_cover(model, cams, out)
        return _reveal(model, views, out)


def _render_cover(model, cams: list[Camera], out: RunFolder) -> int:
    for cam in cams:
        save_png(out.renders / png_name(cam.name, "public_"), model.render(cam)["image"].clamp(0, 1))
    print(f"no key: rendered the cover scene only ({len(cams)} views in {out.renders})")
    return 0


def _reveal(model, views: KeyViews, out: RunFolder) -> int:
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
    return scene.evaluation_views


def cmd_demo(args) -> int:
    from . import build_parser

    argv = ["hide", "--out", args.out, "--iterations", str(args.iterations)]
    argv += ["--quiet"] if args.quiet else []
    argv += ["--force"] if args.force else []
    argv += ["--device", args.device] if args.device else []
    return cmd_hide(build_parser().parse_args(argv))


def add_parsers(sub) -> None:
    p = sub.add_parser("hide", help="train a container hiding a payload (or several, each behind its own key); "
                                    "write the public release and the keys")
    common.add_config_flags(p, common.SCENE_FLAGS + common.TRAIN_FLAGS + SECURE_FLAGS, HIDE_DEFAULTS)
    common.add_run_arguments(p, default_out="runs/secure")
    p.add_argument("--key-out", help="where the (first) secret's key is written (default: OUT/key.safetensors, "
                                     "or OUT/key.sealed when sealed)")
    p.add_argument("--passphrase-env", help="seal the (first) secret's key and the run's checkpoints with the "
                                            "passphrase in this environment variable")
    p.add_argument("--and", dest="more", nargs=argparse.REMAINDER, metavar="SECRET",
                   help="another secret behind its own key: --and --payload P --key-out FILE [--passphrase-env VAR]; "
                        "repeatable; the run's options go before the first --and")
    p.set_defaults(func=cmd_hide)

    p = sub.add_parser("reveal", help="open a release: with the key the hidden payload (the key holds the cameras), "
                                      "without it the cover scene from --scene's cameras")
    p.add_argument("release", help="the release folder (point_cloud.ply + MLPs)")
    p.add_argument("--key", help="the key file; without it only the cover scene renders")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--out", default="revealed", help="folder for the renders (default: revealed)")
    p.add_argument("--force", action="store_true", help="replace an earlier reveal in --out (nothing else)")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    common.add_config_flags(p, common.SCENE_FLAGS, {"scene.source": "none; needed without --key"})
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
