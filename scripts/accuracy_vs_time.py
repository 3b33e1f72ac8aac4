"""Accuracy against time: what each accuracy knob costs, measured on the same scenes in one run.

    python scripts/accuracy_vs_time.py --sections raster           # CPU: 2k Gaussians vs the float64
                                                                   # reference, 20k for timing
    python scripts/accuracy_vs_time.py --sections raster --large   # GPU: 1M at 1920×1080 for timing

A sweep *section* is a function ``(args) -> rows`` (one dict per point and scene) registered in
``SECTIONS`` with the columns its plot draws: ``x`` a time (lower is better) and ``y`` an accuracy
(higher is better). Rows share ``section``, ``scene`` and ``point``; other keys are the section's own
columns. The rasterizer section moves one knob at a time away from the default (alpha_min,
transmittance_min, radius_rule, tile_size, fast_math, color_storage) and measures, per point:

- error on a small scene (``--small``) against the float64 dense reference (tests/reference.py)
  rendered with the *default* options, so that a knob's error is its departure from the exact
  default render: image PSNR and the largest relative gradient error over the inputs (as
  tests/raster_cases.py computes it), for the same random cotangents;
- error on the timing scene (``--large`` or ``--timing``), too big for the dense reference, against
  the default configuration's own float32 render: image PSNR and relative gradient error;
- time on both: median forward and forward+backward over ``--rounds`` rounds that visit every point
  in turn (so that load from other processes falls on all points alike); CUDA events on the GPU,
  perf_counter on the CPU (bench_rasterizer.timed).

Scenes are bench_rasterizer.make_scene's, with the scales multiplied by 1920/width so that the
Gaussians cover as many pixels as in the 1080p benchmark (1M at 1920×1080 is its scene unchanged).

The model section trains Scaffold-GS (ScaffoldTrainer, the CLI's tile size for the device) on the
built-in synthetic scene (--width × --height, --train-views/--test-views) for --iterations from
scratch, moving one knob at a time from TrainConfig's defaults: Gaussians per anchor k (n_offsets
5/10/20), feat_dim (16/32/64; also the MLPs' hidden width) and the feature bank on; the default
model is also evaluated with its anchor features rounded to float16 (half-precision storage). Per point:
held-out PSNR and SSIM (trainer.evaluate), render_ms (ms per held-out frame, from evaluate's
render_fps over --rounds passes), train_s and step_ms (step() wall time only), anchors and
gaussians (those the first held-out view keeps after culling). Its plot draws render_ms, not train
time: k and the MLP width are paid at every frame a viewer draws, training once.

The training section trains the default configuration once and evaluates at 10/25/50/100% of
--iterations: held-out PSNR against train_s (trainer.train_seconds, which counts step() only, so
evaluation does not pollute it). Both sections warm up a throwaway trainer first so that kernel
compilation is not timed.

    python scripts/accuracy_vs_time.py --sections model,training           # CPU: 64×48, 150 iterations
    python scripts/accuracy_vs_time.py --sections model,training --large   # GPU: 1920×1080, 2000 iterations

Writes accuracy_vs_time.csv, accuracy_vs_time.md and accuracy_vs_time.png (time against PSNR per
section and scene, Pareto front marked) to --out and prints the markdown table last.
"""
import argparse
import csv
import dataclasses
import datetime
import math
import os
import statistics
import sys
from pathlib import Path
from typing import Callable

import torch
import warp as wp

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "scripts"), str(ROOT / "tests")]  # bench_rasterizer; reference, raster_cases

import bench_rasterizer  # noqa: E402
import reference  # noqa: E402
from raster_cases import reference_kwargs, relative_error  # noqa: E402
from securegs_warp import rasterize  # noqa: E402

# One knob at a time away from the default (1/255, 1e-4, opacity_aware, 16, off, float32):
# knob -> {label: value}.
RASTER_KNOBS = {
    "alpha_min": {"1/128": 1 / 128, "1/64": 1 / 64, "1/32": 1 / 32},
    "transmittance_min": {"1e-3": 1e-3, "1e-2": 1e-2},
    "radius_rule": {"3sigma": "3sigma", "tight": "tight"},
    "tile_size": {"8": 8, "32": 32},
    "fast_math": {"on": True},
    "color_storage": {"float16": "float16"},
}


@dataclasses.dataclass(frozen=True)
class Section:
    """A sweep: ``run(args)`` returns rows; the plot draws row[x] (a time) against row[y] (an accuracy)."""

    run: Callable[[argparse.Namespace], list]
    x: str
    y: str


def pareto_front(points):
    """Indices of the (time, accuracy) points that no other point beats: none is at least as fast
    and at least as accurate while strictly better in one of the two.

    >>> pareto_front([(1.0, 30.0), (2.0, 40.0), (3.0, 35.0), (1.0, 20.0), (2.0, 40.0)])
    [0, 1, 4]
    """
    return [i for i, (t, a) in enumerate(points)
            if not any(t2 <= t and a2 >= a and (t2 < t or a2 > a) for t2, a2 in points)]


# ---------------------------------------------------------------------------------------------
# The rasterizer section


def raster_points():
    """[(label, rasterize options)]: the default, then each knob value alone."""
    points = [("default", {})]
    for knob, values in RASTER_KNOBS.items():
        points += [(f"{knob}={label}", {knob: value}) for label, value in values.items()]
    return points


@dataclasses.dataclass
class RasterScene:
    """One render's inputs: ``tensors`` means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,3]
    (leaves requiring grad); ``cotangents`` ([H,W,3], [H,W,1]) weigh image and alpha in the loss."""

    name: str
    tensors: dict
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    cotangents: tuple


def make_raster_scene(kind, n, width, height, device):
    """bench_rasterizer's scene, scales × 1920/width: pixel footprints as in its 1080p benchmark."""
    tensors = bench_rasterizer.make_scene(kind, n, device)
    tensors["scales"] *= 1920 / width
    for t in tensors.values():
        t.requires_grad_(True)
    viewmat, K = bench_rasterizer.camera(width, height, device)
    g = torch.Generator().manual_seed(1)
    cotangents = (torch.randn(height, width, 3, generator=g).to(device),
                  torch.randn(height, width, 1, generator=g).to(device))
    return RasterScene(f"{kind} {n:,} @ {width}×{height}", tensors, viewmat, K, width, height, cotangents)


def render_with_grads(scene, **options):
    """Our render: {"image": [H,W,3] float64 CPU, "grads": {input: float64 CPU}, "intersections"} for
    the scene's cotangents."""
    leaves = {name: t.detach().clone().requires_grad_(True) for name, t in scene.tensors.items()}
    image, alpha, info = rasterize(**leaves, viewmat=scene.viewmat, K=scene.K, width=scene.width,
                                   height=scene.height, **options)
    ((image * scene.cotangents[0]).sum() + (alpha * scene.cotangents[1]).sum()).backward()
    return {"image": image.detach().double().cpu(), "grads": {n: t.grad.double().cpu() for n, t in leaves.items()},
            "intersections": int(info["n_intersections"])}


def render_reference(scene):
    """The float64 dense reference with the default options, same output layout as render_with_grads."""
    leaves = {name: t.detach().cpu().double().requires_grad_(True) for name, t in scene.tensors.items()}
    image, alpha, _, _ = reference.render(**leaves, viewmat=scene.viewmat.cpu().double(), K=scene.K.cpu().double(),
                                          width=scene.width, height=scene.height, **reference_kwargs({}))
    w_image, w_alpha = (c.cpu().double() for c in scene.cotangents)
    ((image * w_image).sum() + (alpha * w_alpha).sum()).backward()
    return {"image": image.detach(), "grads": {n: t.grad for n, t in leaves.items()}}


def errors(ours, target):
    """Image PSNR (dB, peak 1; inf when identical) and the largest relative gradient error over the inputs."""
    mse = float(((ours["image"] - target["image"]) ** 2).mean())
    grad_errors = {name: relative_error(g, target["grads"][name]) for name, g in ours["grads"].items()}
    worst = max(grad_errors, key=grad_errors.get)
    return {"psnr_db": 10 * math.log10(1 / mse) if mse > 0 else math.inf,
            "grad_rel_err": grad_errors[worst], "worst_grad": worst}


def median_times(scene, points, device, rounds):
    """{label: (forward ms, forward+backward ms)}: medians over rounds that visit every point in turn."""
    def call(options):
        return lambda: bench_rasterizer.ours(scene.tensors, scene.viewmat, scene.K, scene.width, scene.height,
                                             **options)

    calls = {label: call(options) for label, options in points}
    for fn in calls.values():  # compile and warm up every variant before timing any
        bench_rasterizer.timed(fn, True, device, 1, 1, scene.cotangents)
    samples = {label: ([], []) for label in calls}
    for _ in range(rounds):
        for label, fn in calls.items():
            with torch.no_grad():
                samples[label][0].append(bench_rasterizer.timed(fn, False, device, 0, 1, scene.cotangents))
            samples[label][1].append(bench_rasterizer.timed(fn, True, device, 0, 1, scene.cotangents))
    return {label: (statistics.median(f), statistics.median(fb)) for label, (f, fb) in samples.items()}


def raster_scene_rows(scene, target, vs, device, rounds):
    """Rows of every knob point on one scene, errors against ``target`` (described by ``vs``)."""
    points = raster_points()
    times = median_times(scene, points, device, rounds)
    rows = []
    for label, options in points:
        ours = render_with_grads(scene, **options)
        rows.append({"section": "raster", "scene": scene.name, "point": label, "fwd_ms": times[label][0],
                     "fwd_bwd_ms": times[label][1], **errors(ours, target), "vs": vs,
                     "intersections": ours["intersections"]})
    return rows


def raster_section(args):
    """The rasterizer's knobs on the small (reference) scene and the timing scene."""
    small = make_raster_scene(args.kind, *args.small, args.device)
    print(f"float64 reference of {small.name} (dense, CPU)...", flush=True)
    rows = raster_scene_rows(small, render_reference(small), "float64 reference", args.device, args.rounds)
    big = make_raster_scene(args.kind, *((1_000_000, 1920, 1080) if args.large else args.timing), args.device)
    print(f"timing scene {big.name}...", flush=True)
    rows += raster_scene_rows(big, render_with_grads(big), "default float32", args.device, args.rounds)
    return rows


# ---------------------------------------------------------------------------------------------
# The model and training sections: Scaffold-GS trained on the built-in synthetic scene

# One knob at a time away from TrainConfig's defaults (k = 10, feat_dim = 32, no feature bank):
# label -> TrainConfig overrides. feat_dim is also the hidden width of Scaffold-GS's MLPs.
MODEL_KNOBS = {"default": {}, "k=5": {"n_offsets": 5}, "k=20": {"n_offsets": 20},
               "feat_dim=16": {"feat_dim": 16}, "feat_dim=64": {"feat_dim": 64},
               "feat_bank=on": {"use_feat_bank": True}}

# Fractions of --iterations at which the training section evaluates.
TRAINING_FRACTIONS = (0.1, 0.25, 0.5, 1.0)


def synthetic_scene(args):
    """The built-in synthetic scene at --width × --height (what ``securegs train`` trains on)."""
    from securegs_warp.data import make_synthetic_scene

    return make_synthetic_scene(width=args.width, height=args.height, n_train=args.train_views,
                                n_test=args.test_views, n_points=args.points)


def scene_label(args):
    return f"synthetic {args.width}×{args.height}, {args.iterations} it"


def make_trainer(scene, args, **overrides):
    """ScaffoldTrainer with the CLI's tile size for the device (8 on the CPU, 16 on the GPU)."""
    from securegs_warp.train import ScaffoldTrainer, TrainConfig

    config = TrainConfig(iterations=args.iterations, tile_size=8 if args.device == "cpu" else 16, **overrides)
    return ScaffoldTrainer(scene, config, device=args.device)


def held_out(trainer, rounds):
    """Held-out PSNR/SSIM, render ms per frame (trainer.evaluate's render_fps over ``rounds`` passes)
    and the Gaussians of the first held-out view after culling."""
    metrics = trainer.evaluate(timing_repeats=rounds)
    with torch.no_grad():
        gaussians = trainer.render(trainer.scene.test[0])["gaussians"]["scales"].shape[0]
    return {"test_psnr_db": metrics["psnr"], "test_ssim": metrics["ssim"], "render_ms": 1000 / metrics["fps"],
            "anchors": metrics["anchors"], "gaussians": gaussians}


def warm_up(scene, args):
    """Two steps and a render of a throwaway trainer, so that kernel compilation is not timed in the
    first point."""
    trainer = make_trainer(scene, args)
    for _ in range(2):
        trainer.step()
    with torch.no_grad():
        trainer.render(scene.test[0])


def model_section(args):
    """Each MODEL_KNOBS point trained for --iterations from scratch; train time is step() only."""
    scene = synthetic_scene(args)
    warm_up(scene, args)
    rows = []
    for label, overrides in MODEL_KNOBS.items():
        print(f"model {label}: training {args.iterations} iterations...", flush=True)
        trainer = make_trainer(scene, args, **overrides)
        for _ in range(args.iterations):
            trainer.step()
        timing = {"train_s": trainer.train_seconds, "step_ms": 1000 * trainer.train_seconds / args.iterations}
        rows.append({"section": "model", "scene": scene_label(args), "point": label, **held_out(trainer, args.rounds),
                     **timing})
        if label == "default":
            rows.append({"section": "model", "scene": scene_label(args), "point": "features float16 storage",
                         **held_out_with_float16_features(trainer, args.rounds), **timing})
    return rows


@torch.no_grad()
def held_out_with_float16_features(trainer, rounds):
    """held_out() of the trained model with its anchor features rounded to float16, as a release that
    stores them in half precision would load them (the MLPs still run in float32, so only the
    feature columns of the file halve; the render time should not move)."""
    feat = trainer.model.feat
    stored = feat.detach().clone()
    feat.copy_(stored.half().float())
    try:
        return held_out(trainer, rounds)
    finally:
        feat.copy_(stored)


def training_section(args):
    """One default run, evaluated at TRAINING_FRACTIONS of --iterations; train_s is trainer.train_seconds,
    which counts step() only, so evaluation does not add to it."""
    scene = synthetic_scene(args)
    warm_up(scene, args)
    trainer = make_trainer(scene, args)
    checkpoints = sorted({max(1, round(f * args.iterations)) for f in TRAINING_FRACTIONS})
    rows = []
    for iteration in checkpoints:
        while trainer.step_count < iteration:
            trainer.step()
        print(f"training: {iteration} iterations, {trainer.train_seconds:.1f} s", flush=True)
        rows.append({"section": "training", "scene": scene_label(args), "point": f"{iteration} it",
                     "train_s": trainer.train_seconds, **held_out(trainer, args.rounds)})
    return rows


# x: render ms per frame for the model section, because a model's size and MLP width are paid at
# every frame a viewer draws, whereas training is paid once (step_ms and train_s are columns too).
SECTIONS = {"raster": Section(raster_section, x="fwd_bwd_ms", y="psnr_db"),
            "model": Section(model_section, x="render_ms", y="test_psnr_db"),
            "training": Section(training_section, x="train_s", y="test_psnr_db")}


# ---------------------------------------------------------------------------------------------
# Outputs


def columns(rows):
    """Union of the rows' keys, in first-seen order."""
    return list(dict.fromkeys(key for row in rows for key in row))


def cell(value):
    if isinstance(value, float):
        if math.isinf(value):
            return "∞ (identical)"
        return f"{value:.1e}" if value != 0 and abs(value) < 1e-2 else f"{value:.2f}"
    return "–" if value is None else str(value)


# What the model and training sections' columns mean, listed under the table when present.
COLUMN_NOTES = {
    "test_psnr_db": "held-out PSNR (dB) of the trained model on the synthetic scene's test views",
    "test_ssim": "held-out SSIM",
    "render_ms": "ms per held-out frame (forward render, trainer.evaluate's render_fps)",
    "anchors": "anchors after training",
    "gaussians": "neural Gaussians the first held-out view keeps after culling",
    "train_s": "training wall time, step() only (evaluation excluded)",
    "step_ms": "train_s per iteration (forward + backward + densification + Adam)",
}


def markdown(rows, title):
    keys = columns(rows)
    lines = [title, "", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(row.get(k)) for k in keys) + " |" for row in rows]
    notes = [f"- {key}: {COLUMN_NOTES[key]}" for key in keys if key in COLUMN_NOTES]
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def place_labels(ax, labels, points):
    """Label each point, moving a label down until it overlaps no earlier one (display space, so
    call it once the figure's layout is final)."""
    renderer = ax.figure.canvas.get_renderer()
    placed = []
    for label, xy in zip(labels, points):
        note = ax.annotate(label, xy, fontsize=7, xytext=(5, 3), textcoords="offset points")
        box = note.get_window_extent(renderer)
        while any(box.overlaps(other) for other in placed):
            note.xyann = (5, note.xyann[1] - 4)
            box = note.get_window_extent(renderer)
        placed.append(box)


def plot(rows, path):
    """One panel per (section, scene): time (x) against accuracy (y), each point labelled, the
    Pareto front joined and ringed. Identical images (PSNR ∞) are drawn on a dotted line above the
    best finite one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = list(dict.fromkeys((row["section"], row["scene"]) for row in rows))
    fig, axes = plt.subplots(1, len(panels), figsize=(7.5 * len(panels), 6), squeeze=False)
    labelled = []
    for ax, (section, scene) in zip(axes[0], panels):
        spec = SECTIONS[section]
        group = [row for row in rows if (row["section"], row["scene"]) == (section, scene)]
        points = [(row[spec.x], row[spec.y]) for row in group]
        finite = [a for _, a in points if math.isfinite(a)]
        ceiling = max(finite, default=0.0) + 5.0
        shown = [(t, a if math.isfinite(a) else ceiling) for t, a in points]
        front = pareto_front(points)
        if len(finite) < len(points):
            ax.axhline(ceiling, ls=":", color="grey")
            ax.annotate("identical (PSNR ∞)", (0.01, ceiling), xycoords=("axes fraction", "data"), fontsize=7,
                        color="grey", xytext=(0, -10), textcoords="offset points")
        ax.scatter(*zip(*shown), color="tab:blue", zorder=2)
        ax.plot(*zip(*sorted(shown[i] for i in front)), "-o", color="tab:red", mfc="none", ms=12, zorder=1,
                label="Pareto front")
        labelled.append((ax, [row["point"] for row in group], shown))
        vs = f" vs {group[0]['vs']}" if "vs" in group[0] else ""
        ax.set(title=f"{section}: {scene}", xlabel=spec.x, ylabel=f"{spec.y}{vs} (higher is better)")
        ax.margins(x=0.12, y=0.06)  # room for the labels of the outermost points
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right")
    fig.tight_layout()
    for ax, labels, points in labelled:
        place_labels(ax, labels, points)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(rows, out, title):
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "accuracy_vs_time.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns(rows))
        writer.writeheader()
        writer.writerows(rows)
    table = markdown(rows, title)
    with open(os.path.join(out, "accuracy_vs_time.md"), "w") as f:
        f.write(table)
    plot(rows, os.path.join(out, "accuracy_vs_time.png"))
    return table


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated, of {list(SECTIONS)}")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--kind", default="realistic", help="bench_rasterizer scene kind: random or realistic")
    parser.add_argument("--small", type=int, nargs=3, default=[2000, 160, 120], metavar=("N", "W", "H"),
                        help="scene compared with the float64 dense reference (its memory grows as N·W·H)")
    parser.add_argument("--timing", type=int, nargs=3, default=[20000, 320, 240], metavar=("N", "W", "H"),
                        help="larger scene, compared with the default configuration")
    parser.add_argument("--large", action="store_true",
                        help="GPU preset: raster timing scene of 1M Gaussians at 1920×1080; model/training "
                             "at 1920×1080 for 2000 iterations")
    parser.add_argument("--iterations", type=int, default=None,
                        help="model/training: iterations per run (default 150, --large 2000)")
    parser.add_argument("--width", type=int, default=None, help="model/training: synthetic scene width "
                                                                "(default 64, --large 1920)")
    parser.add_argument("--height", type=int, default=None, help="model/training: synthetic scene height "
                                                                 "(default 48, --large 1080)")
    parser.add_argument("--train-views", type=int, default=16, help="model/training: synthetic training views")
    parser.add_argument("--test-views", type=int, default=4, help="model/training: synthetic held-out views")
    parser.add_argument("--points", type=int, default=None,
                        help="model/training: initial points, one anchor per voxel (default 1000, --large 4000)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds over all points")
    parser.add_argument("--out", default=os.environ.get("OUT") or "runs/accuracy_vs_time")
    args = parser.parse_args()
    unknown = set(args.sections.split(",")) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; known: {list(SECTIONS)}")
    preset = (2000, 1920, 1080, 4000) if args.large else (150, 64, 48, 1000)
    for name, value in zip(("iterations", "width", "height", "points"), preset):
        if getattr(args, name) is None:
            setattr(args, name, value)
    wp.config.quiet = True
    wp.init()

    rows = [row for name in args.sections.split(",") for row in SECTIONS[name].run(args)]
    device = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU ({os.cpu_count()} cores)"
    title = (f"{device}, warp {wp.__version__}, torch {torch.__version__}, {datetime.date.today()}; "
             f"times: median of {args.rounds} interleaved rounds, ms")
    print(write(rows, args.out, title))


if __name__ == "__main__":
    main()
