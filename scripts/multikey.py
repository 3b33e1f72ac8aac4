"""The cost of each extra secret in one release: 1, 2 and 3 secrets against plain Scaffold-GS.

Trains, per seed and one at a time, plain Scaffold-GS and SecureGS containers hiding the first 1, 2
and 3 of ``--secrets`` (each secret with its own private heads and key), on the same synthetic cover,
seed and budget, and prints two markdown tables:

- per model: cover PSNR (Δ vs plain), release size (× plain), anchors, and the leak of the hidden
  object into the anchor cloud: density ratio and coverage near its surface (``compare.density_ratio``,
  ``secure.security.exposure``; docs/results.md "Geometric security");
- per model, key and payload: the hidden PSNR of that key's render against that payload's targets,
  beside the PSNR of the best flat image of the targets (a render that holds nothing of them scores
  at most that), and the bit test of that key's decoded message against that payload's message
  (present when its binomial p-value is at or below verify's alpha). A key's own payload is the
  diagonal; every other cell is a key applied to a payload it does not own.

Last, every key is verified (``verify_message``, as ``securegs verify``) against the releases it was
not made for: the plain models and the other containers of every seed.

    python scripts/multikey.py --out runs/multikey --seeds 0,1
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from securegs_warp.cli.common import cpu_threads, quiet_warp
from securegs_warp.compare import density_ratio, release_mb, train
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.data.synthetic import make_synthetic_scene
from securegs_warp.io.atomic import atomic_write
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.payload import SECRET_SEPARATOR
from securegs_warp.secure.security import exposure
from securegs_warp.secure.trainer import flat_image_psnr
from securegs_warp.secure.verification import DEFAULT_ALPHA, binomial_tail, verify_message
from securegs_warp.train.losses import psnr
from securegs_warp.train.trainer import ScaffoldTrainer

PLAIN = "plain Scaffold-GS"


def hidden_targets(trainer: SecureTrainer, secret: int) -> list[tuple]:
    """(camera, camera index or None, target [H, W, 3]) of each view that shows secret ``secret``'s
    payload: the held-out views of an object or scene, the one view of an image; [] for bits."""
    p, scene = trainer.payloads[secret], trainer.scene
    if p.views is not None and p.test_views is not None:
        return [(cam, None, t) for cam, t in zip(scene.test, p.test_views)]
    if p.views is not None:
        return [(cam, i, t) for i, (cam, t) in enumerate(zip(scene.train, p.views))]
    if p.image is not None:
        return [(scene.train[p.image_view], p.image_view, p.image)]
    return []


@torch.no_grad()
def key_by_payload(trainer: SecureTrainer) -> list[dict]:
    """One row per (key i, payload j) of a container (see the module docstring)."""
    rows = []
    for i, key in enumerate(trainer.model.secrets):
        decoded = trainer.model.decode_bits(secret=i) if key.bits is not None else None
        for j, p in enumerate(trainer.payloads):
            row = {"key": i + 1, "payload": j + 1, "payload_spec": p.spec.describe()}
            targets = hidden_targets(trainer, j)
            if targets:
                row["psnr_flat"] = flat_image_psnr([t for _, _, t in targets])
                if key.decoder is not None:
                    renders = [trainer.render_hidden(cam, index, secret=i)["image"].clamp(0, 1)
                               for cam, index, _ in targets]
                    row["psnr_hidden"] = float(np.mean([psnr(r, t) for r, (_, _, t) in zip(renders, targets)]))
            if p.bits is not None and decoded is not None and len(decoded) == len(p.bits):
                if i == j:
                    anchors = trainer.model.anchors
                    result = verify_message(key.bits, anchors.feat, anchors.xyz)
                    matched, p_value = result.matched, result.p_value
                else:  # key i's reading of the release against payload j's message
                    matched = int((decoded == p.bits.long()).sum())
                    p_value = binomial_tail(matched, len(p.bits))
                row.update(matched=matched, bits=len(p.bits), p_value=p_value, present=p_value <= DEFAULT_ALPHA)
            rows.append(row)
    return rows


def model_row(trainer, base: dict | None, scene, radius: float) -> dict:
    ev = trainer.evaluate(timing_repeats=1)
    xyz = trainer.model.anchors.xyz.detach().cpu().numpy()
    row = {"psnr_public": ev["psnr"], "size_mb": release_mb(trainer.model), "anchors": ev["anchors"],
           "train_seconds": round(trainer.train_seconds, 1),
           "exposure": exposure(xyz, scene.hidden_points, scene.points, radius)}
    if base is not None:
        row.update(delta_psnr=row["psnr_public"] - base["psnr_public"], size_ratio=row["size_mb"] / base["size_mb"],
                   density_ratio=density_ratio(row["exposure"], base["exposure"]))
    return row


def fmt(value, spec=".2f") -> str:
    return "–" if value is None else format(value, spec)


def tables(results: list[dict]) -> str:
    lines = ["| seed | secrets | cover PSNR (Δ vs plain) | release MB (×) | anchors | density ratio | coverage | "
             "training s |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        m = r["model"]
        delta = "" if "delta_psnr" not in m else f" ({m['delta_psnr']:+.2f})"
        ratio = "" if "size_ratio" not in m else f" ({m['size_ratio']:.2f}×)"
        lines.append(f"| {r['seed']} | {r['label']} | {m['psnr_public']:.2f}{delta} | {m['size_mb']:.2f}{ratio} | "
                     f"{m['anchors']:,} | {fmt(m.get('density_ratio'))} | {m['exposure']['coverage']:.3f} | "
                     f"{m['train_seconds']:.0f} |")
    lines += ["", "| seed | secrets | key | payload | hidden PSNR (flat image) | verify: bits agreeing, p-value |",
              "|---|---|---|---|---|---|"]
    for r in results:
        for c in r.get("keys", []):
            hidden = ("–" if "psnr_flat" not in c else
                      f"{fmt(c.get('psnr_hidden'))} ({c['psnr_flat']:.2f})" if "psnr_hidden" in c else
                      f"renders nothing ({c['psnr_flat']:.2f})")
            bits = ("–" if "p_value" not in c else
                    f"{'present' if c['present'] else 'absent'}: {c['matched']}/{c['bits']}, p = {c['p_value']:.2g}")
            mark = "**" if c["key"] == c["payload"] else ""
            lines.append(f"| {r['seed']} | {r['label']} | {mark}{c['key']}{mark} | {c['payload']} "
                         f"({c['payload_spec']}) | {hidden} | {bits} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/multikey", help="folder for multikey.json and multikey.md")
    ap.add_argument("--seeds", default="0,1", help="training and scene seeds, comma-separated (default: 0,1)")
    ap.add_argument("--secrets", default="object+bits:48;bits:48;image+bits:48",
                    help="the secrets, ';'-separated: the containers hide the first 1, 2, 3 ... of them")
    ap.add_argument("--mode", default="cover", help="density strategy of the containers (default: cover)")
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--train-views", type=int, default=32)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    quiet_warp()
    torch.set_num_threads(cpu_threads())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    secrets = args.secrets.split(";")
    meta = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "device": args.device, "width": args.width,
            "height": args.height, "train_views": args.train_views, "test_views": args.test_views,
            "iterations": args.iterations, "mode": args.mode, "secrets": secrets, "alpha": DEFAULT_ALPHA}
    results, models = [], []  # models: (seed, label, anchors, keys' bit decoders)
    for seed in (int(s) for s in args.seeds.split(",")):
        scene = make_synthetic_scene(hidden="mug", level="object", width=args.width, height=args.height,
                                     n_train=args.train_views, n_test=args.test_views, seed=seed, device=args.device)
        config = TrainConfig(iterations=args.iterations, seed=seed, raster=RasterOptions.for_device(args.device))
        radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
        plain = ScaffoldTrainer(scene, config, device=args.device)
        train(plain, f"seed {seed}, plain")
        base = model_row(plain, None, scene, radius)
        results.append({"seed": seed, "label": PLAIN, "model": base})
        models.append((seed, PLAIN, plain.model.anchors, []))
        for count in range(1, len(secrets) + 1):
            payload = SECRET_SEPARATOR.join(secrets[:count])
            strategy = dataclasses.replace(SecureConfig().strategy, mode=args.mode)
            secure = SecureConfig(payload=payload, strategy=strategy)
            trainer = SecureTrainer(scene, config, secure, device=args.device)
            label = f"{count}: {payload}"
            train(trainer, f"seed {seed}, {label}")
            results.append({"seed": seed, "label": label, "model": model_row(trainer, base, scene, radius),
                            "keys": key_by_payload(trainer)})
            models.append((seed, label, trainer.model.anchors,
                           [k.bits for k in trainer.model.secrets if k.bits is not None]))
            write(out, meta, results, [])
        print(tables([r for r in results if r["seed"] == seed]), flush=True)
    foreign = [{"key_of": f"seed {s}, {label}", "release": f"seed {s2}, {label2}",
                **verify_message(decoder, anchors.feat.detach(), anchors.xyz).to_json()}
               for s, label, _, decoders in models for decoder in decoders
               for s2, label2, anchors, _ in models if (s, label) != (s2, label2)]
    write(out, meta, results, foreign)
    print(tables(results))
    if foreign:
        p_values = [f["p_value"] for f in foreign]
        print(f"\nkeys against releases they were not made for: {sum(f['present'] for f in foreign)} of "
              f"{len(foreign)} verified present (alpha {DEFAULT_ALPHA:g}); bit accuracy "
              f"{min(f['bit_accuracy'] for f in foreign):.3f}–{max(f['bit_accuracy'] for f in foreign):.3f}, "
              f"smallest p-value {min(p_values):.2g}")


def write(out: Path, meta: dict, results: list[dict], foreign: list[dict]) -> None:
    """multikey.json and multikey.md, atomically, after every model (a later failure loses nothing)."""
    data = json.dumps({"meta": meta, "results": results, "foreign": foreign}, indent=1).encode()
    atomic_write(out / "multikey.json", lambda f: f.write(data))
    text = tables(results).encode()
    atomic_write(out / "multikey.md", lambda f: f.write(text + b"\n"))


if __name__ == "__main__":
    main()
