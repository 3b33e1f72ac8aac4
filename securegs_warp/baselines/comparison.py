"""The paper's comparison on one synthetic scene: Scaffold-GS and plain 3DGS (the covers without a
payload), SecureGS, 3DGS + StegaNeRF and GS-Hider, with one
payload and one iteration budget. ``scripts/compare_methods.py`` is its command line.

Per method: cover PSNR/SSIM on the held-out views, hidden PSNR/SSIM, FPS of the public and the
hidden render, release size and format, the geometric leakage of the public primitives where the
payload has a surface (``secure.security.exposure``: anchors for Scaffold-GS and SecureGS, Gaussian
means for the explicit methods; the density ratio is over the cover model of the same kind), and
the hidden PSNR after each attack of ``attacks`` (``securegs_warp.attacks`` on anchor releases,
``gaussians.attacks`` on explicit ones).

Each method's runner returns ``(row, public_xyz)``: ``row`` with the keys of ``COLUMNS`` it can
fill (``hidden_psnr_after`` a {spec: PSNR} dict) and ``public_xyz`` [N, 3] the public primitives'
positions (None when it cannot hide the payload: then ``row["note"]`` says why); GS-Hider's is
``gs_hider.compare_row``.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from .. import evaluation
from ..attacks import AttackContext, parse_attacks
from ..compare import release_mb
from ..config import SecureConfig, StegaNeRFConfig, TrainConfig
from ..gaussians.attacks import attack_gaussians
from ..io.atomic import atomic_write, save_figure
from ..robustness import attacked_copy
from ..secure import SecureTrainer
from ..secure.security import exposure
from ..strategies import RegionAwareStrategy
from ..train import GaussianTrainer, ScaffoldTrainer
from ..train.base import psnr_label
from .gs_hider import compare_row as gs_hider_row
from .steganerf import StegaNeRF, hidden_image_for

PAYLOADS = ("image", "object")
# Attacks scored on every release they apply to: moderate strengths of the robustness sweep's kinds.
DEFAULT_ATTACKS = ("prune-random:0.1", "noise-xyz:0.01", "quantize:8", "half", "export-roundtrip")
COLUMNS = ("method", "payload", "psnr_public", "ssim_public", "psnr_hidden", "ssim_hidden", "fps_public",
           "fps_hidden", "release_mb", "release_format", "primitives", "density_ratio", "coverage",
           "train_seconds", "note")

# The methods' own numbers (Mip-NeRF360, 1080p-class images, 30k steps), quoted beside ours.
PAPER = {
    "SecureGS paper, object hiding (Tab. 1, scene-level)": {"psnr_public": 27.75, "psnr_hidden": 32.28,
                                                             "fps": 131.71, "release_mb": 267.39},
    "GS-Hider per SecureGS paper (Tab. 1)": {"psnr_public": 26.59, "psnr_hidden": 30.62, "fps": 48.28,
                                             "release_mb": 468.63},
    "3DGS+StegaNeRF per SecureGS paper (Tab. 1)": {"psnr_public": 26.53, "psnr_hidden": 29.82, "fps": 35.09,
                                                   "release_mb": 1106.67},
    "SecureGS paper, image hiding (Tab. 2)": {"psnr_public": 27.26, "psnr_hidden": 42.99, "fps": 144.46,
                                              "release_mb": 155.09},
    "GS-Hider per SecureGS paper (Tab. 2)": {"psnr_public": 26.64, "psnr_hidden": 42.16, "fps": 57.35,
                                             "release_mb": 385.41},
    "3DGS+StegaNeRF per SecureGS paper (Tab. 2)": {"psnr_public": 20.96, "psnr_hidden": 38.38, "fps": 52.94,
                                                   "release_mb": 842.51},
    "third-party, scene hiding: GS-Hider": {"psnr_public": 25.82, "psnr_hidden": 25.18, "fps": 45.0},
    "third-party, scene hiding: SecureGS": {"psnr_public": 26.57, "psnr_hidden": 23.68, "fps": 36.0},
}


@dataclasses.dataclass
class Setup:
    """What every method shares: the scene, the payload ("image": the builtin emblem; "object": the
    scene's hidden object), the budget (``train.iterations``), the rasterizer, the attacks, and where
    to print progress.

    hidden_image: [H, W, 3] on ``device`` (image payload). radius: the exposure radius (3% of the
    hidden object's diagonal). steganerf: StegaNeRF's options; its ``iterations`` are the
    fine-tuning steps after the 3DGS cover's ``train.iterations``."""

    scene: object
    payload: str
    train: TrainConfig
    device: torch.device
    attacks: tuple
    hidden_image: torch.Tensor
    radius: float
    steganerf: StegaNeRFConfig
    log: object = print

    def progress(self, label: str, total: int, describe):
        """An ``on_step(step, stats)`` callback that logs ``label``'s progress ten times over ``total``
        steps; ``describe(stats)`` says what to show besides the step and the seconds so far."""
        t0, every = time.perf_counter(), max(1, total // 10)

        def on_step(step, stats):
            if step % every == 0:
                self.log(f"  {label} {step}/{total}  {describe(stats)}  {time.perf_counter() - t0:.0f} s")

        return on_step

    @property
    def parsed_attacks(self) -> list:
        """``attacks`` as ``Attack`` objects; none when the comparison scores no attack."""
        return parse_attacks(self.attacks) if self.attacks else []

    @property
    def background(self):
        bg = self.scene.background
        return None if bg is None else torch.tensor(bg, dtype=torch.float32, device=self.device)


def make_setup(scene, payload: str, iterations: int, finetune: int, raster, device, attacks=DEFAULT_ATTACKS,
               log=print, seed: int = 0, steganerf: dict | None = None) -> Setup:
    """The shared setup; ``seed`` seeds every method's training, ``steganerf`` holds
    ``StegaNeRFConfig`` fields other than its iterations (``finetune``). Bad options raise ValueError
    before any training."""
    if payload not in PAYLOADS:
        raise ValueError(f"payload must be one of {', '.join(PAYLOADS)}, got {payload!r}")
    if attacks:
        parse_attacks(attacks)  # a bad spec fails before any training
    radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0))) if scene.hidden_points is not None \
        else 0.0
    return Setup(scene, payload, TrainConfig(iterations=iterations, seed=seed, raster=raster),
                 device, tuple(attacks), torch.as_tensor(hidden_image_for(scene), device=device), radius,
                 StegaNeRFConfig(iterations=finetune, **(steganerf or {})), log)


def _train(trainer, label: str, setup: Setup) -> None:
    t0, total = time.perf_counter(), trainer.total_steps
    every = max(1, total // 10)
    while trainer.step_count < total:
        stats = trainer.step()
        if trainer.step_count % every == 0:
            size = stats.get("anchors", stats.get("gaussians"))
            setup.log(f"  {label}: step {trainer.step_count}/{total}  {psnr_label(stats)} {stats['psnr']:.2f}  "
                      f"size {size}  {time.perf_counter() - t0:.0f} s")


def _leakage(setup: Setup, xyz: np.ndarray | None) -> dict | None:
    if setup.payload != "object" or xyz is None:
        return None
    return exposure(xyz, setup.scene.hidden_points, setup.scene.points, setup.radius)


def _ply_mb(model) -> float:
    with tempfile.TemporaryDirectory() as d:
        model.save_ply(Path(d) / "p.ply")
        return (Path(d) / "p.ply").stat().st_size / 1e6


# -- the methods ----------------------------------------------------------------------------------


def run_scaffold(setup: Setup) -> tuple[dict, np.ndarray]:
    trainer = ScaffoldTrainer(setup.scene, setup.train, device=setup.device)
    _train(trainer, "Scaffold-GS", setup)
    ev = trainer.evaluate()
    return ({"method": "Scaffold-GS", "psnr_public": ev["psnr"], "ssim_public": ev["ssim"], "fps_public": ev["fps"],
             "release_mb": release_mb(trainer.model), "release_format": "Scaffold-GS (anchor PLY + MLPs)",
             "primitives": f"{ev['anchors']} anchors", "train_seconds": trainer.train_seconds},
            trainer.model.anchors.xyz.detach().cpu().numpy())


def run_3dgs(setup: Setup) -> tuple[dict, np.ndarray, GaussianTrainer]:
    config = dataclasses.replace(setup.train, model="3dgs")
    trainer = GaussianTrainer(setup.scene, config, device=setup.device)
    _train(trainer, "3DGS", setup)
    ev = trainer.evaluate()
    return ({"method": "3DGS", "psnr_public": ev["psnr"], "ssim_public": ev["ssim"], "fps_public": ev["fps"],
             "release_mb": _ply_mb(trainer.model), "release_format": "standard 3DGS PLY (SH degree 3)",
             "primitives": f"{ev['gaussians']} Gaussians", "train_seconds": trainer.train_seconds},
            trainer.model.means.detach().cpu().numpy(), trainer)


def run_steganerf(setup: Setup, cover: GaussianTrainer) -> tuple[dict, np.ndarray | None]:
    if setup.payload != "image":
        return {"method": "3DGS+StegaNeRF", "note": "hides 2D images only (decoded from a render)"}, None
    stega = StegaNeRF(cover.model, setup.scene, setup.hidden_image, setup.steganerf,
                      raster=setup.train.raster, background=setup.background, seed=setup.train.seed)
    t0 = time.perf_counter()
    stega.train(setup.progress("3DGS+StegaNeRF: fine-tune", setup.steganerf.iterations,
                               lambda stats: f"hidden mse {stats['hidden']:.4f}  rgb mse {stats['rgb']:.5f}"))
    seconds = cover.train_seconds + time.perf_counter() - t0
    ev = stega.evaluate()
    after = {}
    generator = torch.Generator().manual_seed(0)
    original = stega.model
    for attack in setup.parsed_attacks:
        stega.model = copy.deepcopy(original)
        report = attack_gaussians(stega.model, attack, generator)
        after[attack.text] = _hidden_psnr_stega(stega) if report["applicable"] else None
    stega.model = original
    return ({"method": "3DGS+StegaNeRF", **ev, "release_mb": _ply_mb(stega.model),
             "release_format": "standard 3DGS PLY (SH degree 3); key: U-Net decoder + classifier",
             "primitives": f"{stega.model.num_gaussians} Gaussians", "train_seconds": seconds,
             "hidden_psnr_after": after,
             "note": f"{setup.train.iterations} 3DGS steps + {setup.steganerf.iterations} fine-tuning steps; "
                     f"hidden image decoded from every held-out view (from the original scene's renders: "
                     f"{ev['psnr_hidden_from_original']:.1f} dB)" + _working_size_note(ev, setup.steganerf)},
            original.means.detach().cpu().numpy())


def _working_size_note(ev: dict, config: StegaNeRFConfig) -> str:
    if ev["psnr_hidden_ceiling"] is None:
        return ""
    return (f"; at the decoder's {config.decoder_size}², as the authors score: {ev['psnr_hidden_working_size']:.2f} dB "
            f"(no decoder of that size scores more than {ev['psnr_hidden_ceiling']:.2f} dB at the view's size)")


@torch.no_grad()
def _hidden_psnr_stega(stega: StegaNeRF) -> float:
    cams = stega.scene.evaluation_views
    return evaluation.image_metrics([(stega.render_hidden(c)["image"], stega.hidden) for c in cams], stega.device,
                                    with_lpips=False)["psnr"]


# SecureGS's density modes in the comparison, by method name: the paper's RDO, and the cover mode that this
# project uses by default for an object (its anchors do not draw the object: docs/results.md, "Geometric
# security"), with the robust training and finishing phase that default brings.
SECUREGS_MODES = {"securegs": ("rdo", "SecureGS"), "securegs_cover": ("cover", "SecureGS cover mode")}
METHODS = ("scaffold", *SECUREGS_MODES, "3dgs", "steganerf", "gs_hider")


def run_securegs(setup: Setup, method: str = "securegs") -> tuple[dict, np.ndarray | None]:
    mode, label = SECUREGS_MODES[method]
    if mode == "cover" and setup.payload != "object":
        return {"method": label, "note": "the cover mode hides 3D objects; an image is hidden with the paper's "
                                         "RDO (the SecureGS row)"}, None
    payload = "image:builtin@0" if setup.payload == "image" else "object"
    secure = SecureConfig(payload=payload, strategy=RegionAwareStrategy(mode=mode))
    trainer = SecureTrainer(setup.scene, setup.train, secure, device=setup.device)
    _train(trainer, label, setup)
    ev, hid = trainer.evaluate(), trainer.evaluate_hidden()
    after = {}
    ctx = AttackContext(setup.scene.evaluation_views, setup.train.raster, setup.background,
                        torch.Generator().manual_seed(0), setup.scene, TrainConfig())
    original = trainer.model
    for attack in setup.parsed_attacks:
        attacked, reports = attacked_copy(original, [attack], ctx)
        trainer.model = attacked
        try:
            after[attack.text] = trainer.evaluate_hidden()["psnr_hidden"] if reports[0]["applicable"] else None
        finally:
            trainer.model = original
    where = "training view 0 (the paper's single-image hiding)" if setup.payload == "image" else "every held-out view"
    phase = f"; {trainer.finish_steps} finishing steps after the joint run" if trainer.finish_steps else ""
    return ({"method": label, "psnr_public": ev["psnr"], "ssim_public": ev["ssim"], "fps_public": ev["fps"],
             "psnr_hidden": hid.get("psnr_hidden"), "ssim_hidden": hid.get("ssim_hidden"),
             "fps_hidden": hid.get("fps_hidden"), "release_mb": release_mb(trainer.model),
             "release_format": "Scaffold-GS (anchor PLY + MLPs); key: private MLPs",
             "primitives": f"{ev['anchors']} anchors", "train_seconds": trainer.train_seconds,
             "hidden_psnr_after": after, "note": f"hidden scored at {where}{phase}"},
            trainer.model.anchors.xyz.detach().cpu().numpy())


def run_all(setup: Setup, methods=("scaffold", "securegs", "3dgs", "steganerf", "gs_hider"), on_row=None) -> list[dict]:
    """Run the methods (names of METHODS) in order; returns one row per method (``on_row(rows)`` after
    each). The density ratio of each anchor model is over Scaffold-GS's, of each explicit model over
    3DGS's. An unknown name, or steganerf without 3dgs before it, raises ValueError before any training."""
    methods = list(methods)
    unknown = [name for name in methods if name not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}: the methods are {', '.join(METHODS)}")
    if "steganerf" in methods and "3dgs" not in methods[:methods.index("steganerf")]:
        raise ValueError("steganerf fine-tunes the 3DGS cover: list 3dgs before it")
    rows, leak, cover = [], {}, None
    for name in methods:
        setup.log(f"{name} ...")
        t0 = time.perf_counter()
        if name == "scaffold":
            row, xyz = run_scaffold(setup)
        elif name == "3dgs":
            row, xyz, cover = run_3dgs(setup)
        elif name == "steganerf":
            row, xyz = run_steganerf(setup, cover)
        elif name in SECUREGS_MODES:
            row, xyz = run_securegs(setup, name)
        else:
            row, xyz = gs_hider_row(setup)
        row = {"payload": setup.payload, **row, "wall_seconds": round(time.perf_counter() - t0, 1)}
        e = _leakage(setup, xyz)
        if e is not None:
            leak[row["method"]] = e
            base = leak.get("Scaffold-GS" if "anchors" in row.get("primitives", "") else "3DGS")
            row["coverage"] = e["coverage"]
            row["density_ratio"] = (e["surface_density"] / base["surface_density"]
                                    if base is not None and base["surface_density"] > 0 else None)
            row["exposure"] = e
        rows.append(row)
        setup.log(f"{row['method']} done in {row['wall_seconds']} s: " + ", ".join(
            f"{k} {v:.4g}" for k, v in row.items() if isinstance(v, float) and k != "wall_seconds"))
        if on_row is not None:
            on_row(rows)
    return rows


# -- the report -----------------------------------------------------------------------------------


def _fmt(value) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:.4g}"
    return str(value)


def report_tables(rows: list[dict], meta: dict) -> str:
    """Markdown: the main table, the attack table (hidden PSNR after each attack) and the papers'
    numbers."""
    lines = [f"{meta['device']}, {meta['width']}×{meta['height']}, {meta['iterations']} iterations "
             f"(3DGS+StegaNeRF: + {meta['finetune']} fine-tuning steps, tune {meta.get('steganerf_tune', 'color')}"
             f"{', antialiased decoder input' if meta.get('steganerf_antialias') else ''}), "
             f"payload {meta['payload']}, seed {meta.get('seed', 0)}, commit {meta.get('commit', '?')}", "",
             "| " + " | ".join(COLUMNS) + " |", "|---" * len(COLUMNS) + "|"]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in COLUMNS) + " |" for r in rows]
    attacked = [r for r in rows if r.get("hidden_psnr_after")]
    if attacked:
        specs = list(dict.fromkeys(s for r in attacked for s in r["hidden_psnr_after"]))
        lines += ["", "Hidden PSNR (dB) after each attack (– : not applicable to that release):", "",
                  "| method | none | " + " | ".join(specs) + " |", "|---" * (len(specs) + 2) + "|"]
        lines += [f"| {r['method']} | {_fmt(r.get('psnr_hidden'))} | "
                  + " | ".join(_fmt(r["hidden_psnr_after"].get(s)) for s in specs) + " |" for r in attacked]
    lines += ["", "Quoted (not run here):", "", "| source | cover PSNR | hidden PSNR | FPS | size (MB) |",
              "|---|---|---|---|---|"]
    lines += [f"| {k} | {v['psnr_public']} | {v['psnr_hidden']} | {v['fps']} | {v.get('release_mb', '–')} |"
              for k, v in PAPER.items()]
    return "\n".join(lines)


def write_report(out: Path, rows: list[dict], meta: dict) -> str:
    """compare_methods.{md,csv,json} in ``out``, atomically; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    table = report_tables(rows, meta)
    csv_columns = list(COLUMNS) + sorted({f"hidden_psnr_after:{s}" for r in rows for s in r.get("hidden_psnr_after", {})})

    def cell(row, column):
        if column.startswith("hidden_psnr_after:"):
            value = row.get("hidden_psnr_after", {}).get(column.split(":", 1)[1])
        else:
            value = row.get(column)
        text = "" if value is None else (f"{value:.6g}" if isinstance(value, float) else str(value))
        return '"' + text.replace('"', "'") + '"' if "," in text else text

    csv = "\n".join([",".join(csv_columns)] + [",".join(cell(r, c) for c in csv_columns) for r in rows]) + "\n"
    atomic_write(out / "compare_methods.md", lambda f: f.write((table + "\n").encode()))
    atomic_write(out / "compare_methods.csv", lambda f: f.write(csv.encode()))
    atomic_write(out / "compare_methods.json",
                 lambda f: f.write(json.dumps({"meta": meta, "rows": rows}, indent=1, default=str).encode()))
    return table


def plot(path: Path, rows: list[dict]) -> None:
    """Cover and hidden PSNR and public / hidden FPS per method (needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ran = [r for r in rows if r.get("psnr_public") is not None]
    names = [r["method"] for r in ran]
    x = np.arange(len(ran))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for offset, key, label in ((-0.2, "psnr_public", "cover"), (0.2, "psnr_hidden", "hidden")):
        axes[0].bar(x + offset, [r.get(key) or 0.0 for r in ran], 0.4, label=label)
    axes[0].set_ylabel("PSNR (dB)")
    for offset, key, label in ((-0.2, "fps_public", "public render"), (0.2, "fps_hidden", "hidden render")):
        axes[1].bar(x + offset, [r.get(key) or 0.0 for r in ran], 0.4, label=label)
    axes[1].set_ylabel("FPS")
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=20, fontsize=8)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
