"""``securegs attack``: apply attacks to a release, write the attacked release, and score what the key
still gets out of it (hidden views, bits) and what the cover keeps."""
from __future__ import annotations

import json
from pathlib import Path

import torch

from ..attacks import ATTACK_SYNTAX, FINETUNE_NEEDS_SCENE, AttackContext, parse_attacks
from ..config import SceneSpec, TrainConfig, apply_overrides, check_seed
from ..io import save_scaffold
from ..io.scaffold import MLP_FILES, POINT_CLOUD_FILE
from ..robustness import attacked_copy, reference_hidden, score_release
from ..runs import RunFolder
from ..secure.container import KeyViews, open_container
from . import common
from .common import CommandError
from .secure import SECURE_FLAGS, passphrase_from

RELEASE_FILES = (POINT_CLOUD_FILE, *MLP_FILES.values())
SCENE_FLAGS = common.SCENE_FLAGS + tuple(f for f in SECURE_FLAGS if f[1] in ("scene.hidden", "scene.level"))


def scene_from(args):
    """The cover's scene from ``--scene`` and the scene options, or None without ``--scene``."""
    given = {name.split(".", 1)[1]: v for name, v in vars(args).items() if name.startswith("scene.") and v is not None}
    if "source" not in given:
        return None
    return apply_overrides(SceneSpec(), given).load()


def prepare_release_folder(out: RunFolder, force: bool) -> None:
    """Refuse an --out that holds anything but an earlier attacked release, and that one without
    --force. Nothing is removed here: ``save_scaffold`` replaces the folder whole once the attacked
    release exists, so a failing attack leaves the earlier one."""
    path = out.path
    if path.exists() and not path.is_dir():
        raise CommandError(f"--out {path} is a file, not a folder")
    if not path.is_dir() or not any(path.iterdir()):
        return
    others = sorted(p.name for p in path.iterdir() if p.name not in RELEASE_FILES)
    if others:
        raise CommandError(f"--out {path} holds other files ({', '.join(others)}); choose a new or empty folder")
    if not force:
        raise CommandError(f"--out {path} holds an earlier release; add --force to replace it")


@torch.no_grad()
def cmd_attack(args) -> int:
    attacks = parse_attacks(args.attack)
    try:
        check_seed(args.seed, "--seed")
    except ValueError as e:
        raise CommandError(str(e)) from None
    device = common.resolve_device(args.device)
    common.quiet_warp()
    scene = scene_from(args)
    if scene is None and any(a.needs_scene for a in attacks):
        raise CommandError(FINETUNE_NEEDS_SCENE)
    passphrase = passphrase_from(args)
    out = RunFolder(args.out)
    if out.path.resolve() == Path(args.release).resolve():
        raise CommandError("--out is the release itself; write the attacked release to another folder")
    model, meta = open_container(args.release, args.key, passphrase, device=device)
    prepare_release_folder(out, args.force)
    views = KeyViews.from_metadata(meta, device)
    reference = reference_hidden(model, views)
    before = score_release(model, views, None, scene)
    ctx = AttackContext(views.hidden or views.cameras, views.raster, views.background,
                        torch.Generator().manual_seed(args.seed), scene, TrainConfig())
    with torch.enable_grad():  # purify's contributions and finetune take gradients
        attacked, reports = attacked_copy(model, attacks, ctx)
    broken = [name for part in (attacked.anchors, attacked.heads) for name, t in part.state_dict().items()
              if t.is_floating_point() and not torch.isfinite(t).all()]
    if broken:
        raise CommandError(f"the attacks ({', '.join(args.attack)}) left non-finite values in {', '.join(broken)}: "
                           "no release can hold them, and nothing was written")
    save_scaffold(out.path, attacked.anchors, attacked.heads)
    heads_changed = any(a.changes_heads for a in attacks)
    # An attack on the MLP weights breaks the key's binding to this release; it is scored anyway,
    # with the key it was made against (see open_container).
    reopened, _ = open_container(out.path, args.key, passphrase, device=device, check_fingerprint=not heads_changed)
    after = score_release(reopened, views, reference, scene)
    result = {"release": str(args.release), "out": str(out.path), "attacks": reports,
              "fingerprint_matches": not heads_changed, "before": before, "after": after}
    if args.json:
        print(json.dumps(result))
        return 0
    for report in reports:
        note = "" if report["applicable"] else f" (not applicable: {report['reason']})"
        print(f"{report['attack']}: anchors {report['anchors_before']} -> {report['anchors_after']}{note}")
    for name, scores in (("before", before), ("after", after)):
        print(f"{name:6s} " + "  ".join(f"{k}={'–' if v is None else format(v, '.4g') if isinstance(v, float) else v}"
                                        for k, v in scores.items()))
    print(f"attacked release in {out.path}" + ("" if not heads_changed else
                                               " (its MLPs changed: the key's fingerprint no longer matches it)"))
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("attack", help="attack a release (pruning, noise, outlier removal, quantisation, purification, "
                                      "fine-tuning) and score what the key still reveals")
    p.add_argument("release", help="the release folder (point_cloud.ply + MLPs)")
    p.add_argument("--key", required=True, help="the release's key file")
    p.add_argument("--attack", action="append", metavar="SPEC",
                   help=f"an attack, repeatable, applied left to right: {', '.join(ATTACK_SYNTAX)}")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--out", default="attacked", help="folder for the attacked release (default: attacked)")
    p.add_argument("--force", action="store_true", help="replace an earlier attacked release in --out (nothing else)")
    p.add_argument("--seed", type=int, default=0, help="random source of the attacks (default: 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object: attacks, before, after")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    # Without --scene nothing is scored against the cover's views or the true hidden views.
    common.add_config_flags(p, SCENE_FLAGS, {"scene.source": "none"})
    p.set_defaults(func=cmd_attack, quiet=True)
