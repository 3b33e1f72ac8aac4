"""Rasterizer benchmarks and accuracy-against-time sweeps: the library behind scripts/bench_rasterizer.py
and scripts/accuracy_vs_time.py, whose scripts only parse arguments and write the tables.

Scenes and timing (shared by the scripts):
    ``make_scene(kind, n, device)`` → {means [N, 3], quats [N, 4], scales [N, 3], opacities [N],
    colors [N, 3]}: gsplat's benchmark set-up; ``camera(width, height, device)`` → (viewmat [4, 4],
    K [3, 3]); ``timed(fn, backward, device, warmup, runs, grads)`` → median milliseconds of ``fn``,
    where ``fn() -> (image [H, W, 3], alpha [H, W, 1])`` and ``grads`` = (image cotangent [H, W, 3],
    alpha cotangent [H, W, 1]) weigh the backward's loss.

Options on the command line:
    ``parse_options("tile_size=8,fast_math=true")`` → ``RasterOptions``; ``parse_variant("NAME:key=value,...")``
    → (NAME, ``RasterOptions``). Both refuse an unknown field, a value of the wrong type or a value
    ``RasterOptions`` refuses, with a ValueError that says which.

The rasterizer benchmark (scripts/bench_rasterizer.py):
    ``benchmark_scene`` times ``rasterize`` (and its variants, and ``gsplat.rasterization`` when it
    is installed and the device is CUDA) on one scene and returns a row of medians, ratios and image
    differences, with ``kernel_breakdown``'s per-kernel CUDA times (torch.profiler) of each renderer
    with its own options when asked;
    ``benchmark_table(rows, ...)`` is the markdown table of the rows.

The accuracy-against-time sweeps (scripts/accuracy_vs_time.py):
    ``SECTIONS`` maps a section name to a ``Section``: ``run(args) -> rows`` (one dict per point and
    scene) and the columns its plot draws, ``x`` a time (lower is better) and ``y`` an accuracy
    (higher is better). "raster" moves one rasterizer knob at a time (``RASTER_KNOBS``) and compares
    with the float64 dense reference (``securegs_warp.reference``) on a small scene and with the
    default float32 render on a timing scene; "model" and "training" train Scaffold-GS on the built-in
    synthetic scene. ``write(rows, out, title)`` writes the CSV, the markdown table and the plot
    (matplotlib, the ``plots`` extra) with each panel's Pareto front.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import math
import os
import statistics
import time
from typing import Callable

import torch

from . import reference
from .io.atomic import atomic_write, save_figure
from .raster_cases import reference_kwargs, relative_error
from .rasterizer import RasterOptions, check_option_names, rasterize, resolve_options

SCENE_KINDS = ("random", "realistic")

# ---------------------------------------------------------------------------------------------
# Scenes and timing


def make_scene(kind: str, n: int, device: str, seed: int = 0) -> dict:
    """Gaussians in an 8×4.5×4 box 6 units in front of the camera (gsplat's benchmark set-up):
    {"means": [N, 3], "quats": [N, 4], "scales": [N, 3], "opacities": [N], "colors": [N, 3]}, float32
    on ``device``.

    kind "random": scales uniform in [0.002, 0.022]. kind "realistic": log-normal scales (median
    0.006, a long tail up to ~0.3), like a trained scene: many small Gaussians, few large ones.
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown scene kind {kind!r}; known: {', '.join(SCENE_KINDS)}")
    if n < 0:
        raise ValueError(f"the number of Gaussians must be >= 0, got {n}")
    g = torch.Generator(device="cpu").manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([8.0, 4.5, 4.0]) + torch.tensor([0.0, 0.0, 6.0])
    quats = torch.randn(n, 4, generator=g)
    if kind == "random":
        scales = torch.rand(n, 3, generator=g) * 0.02 + 0.002
        opacities = torch.rand(n, generator=g)
    else:
        scales = torch.exp(torch.randn(n, 3, generator=g) * 0.8 + math.log(0.006)).clamp(max=0.3)
        opacities = torch.sigmoid(torch.randn(n, generator=g) * 2.0)
    colors = torch.rand(n, 3, generator=g)
    return {k: v.to(device) for k, v in dict(means=means, quats=quats, scales=scales, opacities=opacities,
                                             colors=colors).items()}


def camera(width: int, height: int, device: str):
    """(viewmat [4, 4] identity, K [3, 3]) looking down +z; the focal length scales with the width
    (1100 px at 1920) so that a scene covers the same part of the image at any resolution."""
    f = 1100.0 * width / 1920.0
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32, device=device)
    return torch.eye(4, device=device), K


def cotangents(width: int, height: int, device: str, seed: int = 1, normal: bool = False):
    """(image cotangent [H, W, 3], alpha cotangent [H, W, 1]), seeded on the CPU: uniform in [0, 1),
    or standard normal with ``normal``."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    draw = torch.randn if normal else torch.rand
    return (draw(height, width, 3, generator=g).to(device), draw(height, width, 1, generator=g).to(device))


def render_call(fn, backward: bool, grads):
    """A callable that renders ``fn() -> (image [H, W, C], alpha [H, W, 1])`` and, with ``backward``,
    backpropagates the loss Σ image·grads[0] + Σ alpha·grads[1]: one timed call of the benchmarks."""
    def once():
        image, alpha = fn()
        if backward:
            (image * grads[0]).sum().add_((alpha * grads[1]).sum()).backward()

    return once


def timed(fn, backward: bool, device: str, warmup: int, runs: int, grads) -> float:
    """Median milliseconds of fn() (and of a backward through it), after ``warmup`` untimed calls.

    ``fn() -> (image [H, W, C], alpha [H, W, 1])``; with ``backward`` the loss
    Σ image·grads[0] + Σ alpha·grads[1] is backpropagated inside the timed region. CUDA events on
    a CUDA ``device``, ``time.perf_counter`` otherwise.
    """
    if runs < 1 or warmup < 0:
        raise ValueError(f"need runs >= 1 and warmup >= 0, got runs={runs}, warmup={warmup}")
    once = render_call(fn, backward, grads)
    for _ in range(warmup):
        once()
    times = []
    for _ in range(runs):
        if on_cuda(device):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            once()
            end.record()
            torch.cuda.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t0 = time.perf_counter()
            once()
            times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def add_scene_arguments(parser: argparse.ArgumentParser) -> None:
    """--device, --sizes, --kinds, --width, --height: the benchmark scenes a script renders."""
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", default="100000,1000000,3000000", help="comma-separated Gaussian counts")
    parser.add_argument("--kinds", default="random,realistic", help=f"of {', '.join(SCENE_KINDS)}")
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)


def ours(scene: dict, viewmat, K, width: int, height: int, options: RasterOptions | None = None):
    """(image [H, W, 3], alpha [H, W, 1]) of ``rasterize`` on a ``make_scene`` scene."""
    image, alpha, _ = rasterize(**scene, viewmat=viewmat, K=K, width=width, height=height, options=options)
    return image, alpha


def on_cuda(device) -> bool:
    """Whether ``device`` ("cuda", "cuda:1", a torch.device ...) is a CUDA device."""
    return torch.device(device).type == "cuda"


def device_label(device) -> str:
    """The GPU's name on CUDA, else "cpu": what the tables name as the machine."""
    return torch.cuda.get_device_name(torch.device(device)) if on_cuda(device) else "cpu"


def gsplat_available(device: str) -> bool:
    """Whether ``gsplat_render`` can run: gsplat is installed and the device is CUDA."""
    if not on_cuda(device):
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def gsplat_render(scene: dict, viewmat, K, width: int, height: int):
    """(image [H, W, 3], alpha [H, W, 1]) of ``gsplat.rasterization`` (classic, packed=False, its
    defaults, which are ``RasterOptions``' defaults) on a ``make_scene`` scene."""
    import gsplat

    image, alpha, _ = gsplat.rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                           scene["colors"], viewmat[None], K[None], width, height, packed=False)
    return image[0], alpha[0]


# ---------------------------------------------------------------------------------------------
# Options on the command line

_BOOLS = {"true": True, "false": False}


def _typed(name: str, text: str):
    """A RasterOptions field's value from its text, by the type of the field's default."""
    default = RasterOptions.__dataclass_fields__[name].default
    if name == "render_depth":
        return None if text.lower() == "none" else text
    if isinstance(default, bool):
        if text.lower() not in _BOOLS:
            raise ValueError(f"option {name}: expected true or false, got {text!r}")
        return _BOOLS[text.lower()]
    for cast, kind in ((int, "an integer"), (float, "a number")):
        if isinstance(default, cast):
            try:
                return cast(text)
            except ValueError:
                raise ValueError(f"option {name}: expected {kind}, got {text!r}") from None
    return text


def parse_options(text: str, base: RasterOptions | None = None) -> RasterOptions:
    """"key=value,key=value" → ``base`` (default ``RasterOptions()``) with those fields replaced.

    Values are typed by the field: integers, numbers, true/false, text, and "none" for render_depth.
    An empty text gives ``base``. Raises ValueError for an item without "=", a repeated or unknown
    field (naming the valid ones), a value of the wrong type, or one ``RasterOptions`` refuses.

    >>> parse_options("tile_size=8,fast_math=true") == RasterOptions(tile_size=8, fast_math=True)
    True
    """
    fields = {}
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq or not key:
            raise ValueError(f"option {item!r} is not key=value")
        if key in fields:
            raise ValueError(f"option {key} given twice")
        fields[key] = value
    check_option_names(fields)
    typed = {key: _typed(key, value) for key, value in fields.items()}
    return resolve_options(base, **typed)


def parse_variant(text: str, base: RasterOptions | None = None):
    """"NAME:key=value,key=value" → (NAME, ``parse_options`` of the rest on ``base``); "NAME" alone is
    ``base``. Raises ValueError as ``parse_options`` does, and for an empty NAME."""
    name, _, spec = text.partition(":")
    name = name.strip()
    if not name:
        raise ValueError(f"variant {text!r} has no name (expected NAME:key=value,...)")
    return name, parse_options(spec, base)


def options_text(options: RasterOptions) -> str:
    """The fields of ``options`` that differ from the defaults, as ``parse_options`` reads them."""
    default = RasterOptions()
    changed = [(f.name, getattr(options, f.name)) for f in dataclasses.fields(options)
               if getattr(options, f.name) != getattr(default, f.name)]
    return ",".join(f"{k}={str(v).lower() if isinstance(v, bool) or v is None else v}" for k, v in changed)


# ---------------------------------------------------------------------------------------------
# The rasterizer benchmark (scripts/bench_rasterizer.py)


def kernel_breakdown(fn, backward: bool, grads, runs: int = 5) -> dict:
    """{kernel name (64 characters): GPU milliseconds per call} of ``fn`` (as ``timed`` takes it, with
    a backward through it when ``backward``), largest first: every CUDA kernel, memset and copy that
    torch.profiler (CUPTI) sees, Warp's and gsplat's alike, averaged over ``runs`` calls after one
    untimed call. CUDA only."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    once = render_call(fn, backward, grads)
    once()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(runs):
            once()
        torch.cuda.synchronize()
    totals = {}
    for event in prof.events():
        if event.device_type == DeviceType.CUDA:
            name = event.name[:64]
            totals[name] = totals.get(name, 0.0) + event.time_range.elapsed_us() / 1000.0 / runs
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def input_gradients(call, scene: dict, grads) -> dict:
    """{input name: its gradient} of Σ image·grads[0] + Σ alpha·grads[1] through ``call()`` (which
    renders ``scene``'s leaf tensors); the leaves' .grad is cleared before and after."""
    for t in scene.values():
        t.grad = None
    render_call(call, True, grads)()
    out = {name: t.grad.clone() for name, t in scene.items()}
    for t in scene.values():
        t.grad = None
    return out


def benchmark_scene(kind: str, n: int, width: int, height: int, device: str, options: RasterOptions | None = None,
                    variants=(), with_gsplat: bool = False, warmup: int = 3, runs: int = 20,
                    breakdown: bool = False) -> dict:
    """Time ``rasterize`` with ``options`` ("ours"), each (name, RasterOptions) of ``variants`` and,
    with ``with_gsplat``, ``gsplat_render`` on ``make_scene(kind, n)`` at width × height.

    Returns a row: scene, n, width, height; NAME_fwd_ms and NAME_fwdbwd_ms (medians of ``runs`` after
    ``warmup``) for every renderer; intersections and visible Gaussians of ours; with gsplat also
    max_image_diff, pixels_over_1e-4, max_alpha_diff, fwd_ratio and fwdbwd_ratio (ours / gsplat), and
    NAME_max_image_diff, NAME_fwd_ratio, NAME_fwdbwd_ratio for each variant; NAME_max_grad_diff, the
    largest over the inputs of a variant's gradient's ``relative_error`` to ours; with ``breakdown``
    (CUDA only) breakdown_ms: {renderer: ``kernel_breakdown`` of its forward+backward}, each
    renderer with its own options.
    """
    options = options or RasterOptions()
    renderers = {"ours": lambda *a: ours(*a, options)}
    for name, variant in variants:
        if name in renderers or name == "gsplat":
            raise ValueError(f"variant name {name!r} is taken (ours, gsplat and each variant need their own)")
        renderers[name] = lambda *a, variant=variant: ours(*a, variant)
    if with_gsplat:
        renderers["gsplat"] = gsplat_render
    scene = make_scene(kind, n, device)
    for t in scene.values():
        t.requires_grad_(True)
    viewmat, K = camera(width, height, device)
    grads = cotangents(width, height, device)
    row = {"scene": kind, "n": n, "width": width, "height": height}
    calls = {name: (lambda fn=fn: fn(scene, viewmat, K, width, height)) for name, fn in renderers.items()}
    for name, call in calls.items():
        with torch.no_grad():
            row[f"{name}_fwd_ms"] = timed(call, False, device, warmup, runs, grads)
        row[f"{name}_fwdbwd_ms"] = timed(call, True, device, warmup, runs, grads)
    with torch.no_grad():
        img, alpha, info = rasterize(**scene, viewmat=viewmat, K=K, width=width, height=height, options=options)
        row["intersections"] = int(info["n_intersections"])
        row["visible"] = int((info["radii"][:, 0] > 0).sum())
        if with_gsplat:
            ref, ref_alpha = gsplat_render(scene, viewmat, K, width, height)
            diff = (img - ref).abs()
            row["max_image_diff"] = float(diff.max())
            row["pixels_over_1e-4"] = int((diff.amax(-1) > 1e-4).sum())
            row["max_alpha_diff"] = float((alpha - ref_alpha).abs().max())
            row["fwd_ratio"] = row["ours_fwd_ms"] / row["gsplat_fwd_ms"]
            row["fwdbwd_ratio"] = row["ours_fwdbwd_ms"] / row["gsplat_fwdbwd_ms"]
            for name, _ in variants:
                row[f"{name}_max_image_diff"] = float((calls[name]()[0] - ref).abs().max())
                row[f"{name}_fwd_ratio"] = row[f"{name}_fwd_ms"] / row["gsplat_fwd_ms"]
                row[f"{name}_fwdbwd_ratio"] = row[f"{name}_fwdbwd_ms"] / row["gsplat_fwdbwd_ms"]
    if variants:
        base = input_gradients(calls["ours"], scene, grads)
        for name, _ in variants:
            other = input_gradients(calls[name], scene, grads)
            row[f"{name}_max_grad_diff"] = max(relative_error(other[key], base[key]) for key in base)
    if breakdown:
        row["breakdown_ms"] = {name: kernel_breakdown(call, True, grads) for name, call in calls.items()}
    return row


def benchmark_table(rows: list, title: str) -> str:
    """``title``, then the markdown table of ``benchmark_scene`` rows: ours, each variant (its
    times, and with gsplat its ratios and image difference) and gsplat's columns when the rows have
    them; then, for rows with a breakdown, a per-kernel table of each renderer."""
    with_gsplat = bool(rows) and "gsplat_fwd_ms" in rows[0]
    names = [k[:-len("_fwd_ms")] for k in rows[0] if k.endswith("_fwd_ms") and k != "gsplat_fwd_ms"] if rows else []
    with_grads = bool(rows) and any(k.endswith("_max_grad_diff") for k in rows[0])
    header = "| scene | N | renderer | fwd ms | fwd+bwd ms |" + (
        " gsplat fwd ms | gsplat fwd+bwd ms | fwd ratio | fwd+bwd ratio | max |Δimage| |" if with_gsplat else "") + (
        " Δgrad vs ours |" if with_grads else "")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        for name in names:
            line = f"| {r['scene']} | {r['n']:,} | {name} | {r[name + '_fwd_ms']:.2f} | {r[name + '_fwdbwd_ms']:.2f} |"
            if with_gsplat:
                prefix = "" if name == "ours" else name + "_"
                line += (f" {r['gsplat_fwd_ms']:.2f} | {r['gsplat_fwdbwd_ms']:.2f} | {r[prefix + 'fwd_ratio']:.2f} |"
                         f" {r[prefix + 'fwdbwd_ratio']:.2f} | {r[prefix + 'max_image_diff']:.1e} |")
            if with_grads:
                line += " — |" if name == "ours" else f" {r[name + '_max_grad_diff']:.1e} |"
            lines.append(line)
    text = title + "\n\n" + "\n".join(lines)
    for r in rows:
        for name, kernels in r.get("breakdown_ms", {}).items():
            text += (f"\n\nPer-kernel GPU time, {r['scene']} {r['n']:,}, {name}, forward+backward "
                     f"(total {sum(kernels.values()):.2f} ms)\n\n| kernel | ms |\n|---|---|\n")
            text += "\n".join(f"| `{k}` | {v:.3f} |" for k, v in kernels.items())
    return text


# ---------------------------------------------------------------------------------------------
# Accuracy against time: sections

# One knob at a time away from the default (1/255, 1e-4, opacity_aware, 16, fast math on, float32,
# packed records): knob -> {label: value}.
RASTER_KNOBS = {
    "alpha_min": {"1/128": 1 / 128, "1/64": 1 / 64, "1/32": 1 / 32},
    "transmittance_min": {"1e-3": 1e-3, "1e-2": 1e-2},
    "radius_rule": {"3sigma": "3sigma"},
    "tile_size": {"8": 8, "32": 32},
    "fast_math": {"off": False},
    "color_storage": {"float16": "float16"},
    "gather": {"fields": "fields"},
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


# The rasterizer section


def raster_points():
    """[(label, RasterOptions)]: the default, then each knob value alone."""
    points = [("default", RasterOptions())]
    for knob, values in RASTER_KNOBS.items():
        points += [(f"{knob}={label}", RasterOptions(**{knob: value})) for label, value in values.items()]
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
    """``make_scene``'s scene, scales × 1920/width: pixel footprints as in the 1080p benchmark (1M at
    1920×1080 is its scene unchanged); standard normal cotangents."""
    tensors = make_scene(kind, n, device)
    tensors["scales"] *= 1920 / width
    for t in tensors.values():
        t.requires_grad_(True)
    viewmat, K = camera(width, height, device)
    return RasterScene(f"{kind} {n:,} @ {width}×{height}", tensors, viewmat, K, width, height,
                       cotangents(width, height, device, normal=True))


def render_for_errors(scene: RasterScene, options: RasterOptions | None = None):
    """Our render: {"image": [H,W,3] float64 CPU, "grads": {input: float64 CPU}, "intersections"} for
    the scene's cotangents."""
    leaves = {name: t.detach().clone().requires_grad_(True) for name, t in scene.tensors.items()}
    image, alpha, info = rasterize(**leaves, viewmat=scene.viewmat, K=scene.K, width=scene.width,
                                   height=scene.height, options=options)
    ((image * scene.cotangents[0]).sum() + (alpha * scene.cotangents[1]).sum()).backward()
    return {"image": image.detach().double().cpu(), "grads": {n: t.grad.double().cpu() for n, t in leaves.items()},
            "intersections": int(info["n_intersections"])}


def render_reference(scene: RasterScene):
    """The float64 dense reference with the default options, same output layout as render_for_errors."""
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
    """{label: (forward ms, forward+backward ms)}: medians over rounds that visit every point in turn
    (so that load from other processes falls on all points alike)."""
    def call(options):
        return lambda: ours(scene.tensors, scene.viewmat, scene.K, scene.width, scene.height, options)

    calls = {label: call(options) for label, options in points}
    for fn in calls.values():  # compile and warm up every variant before timing any
        timed(fn, True, device, 1, 1, scene.cotangents)
    samples = {label: ([], []) for label in calls}
    for _ in range(rounds):
        for label, fn in calls.items():
            with torch.no_grad():
                samples[label][0].append(timed(fn, False, device, 0, 1, scene.cotangents))
            samples[label][1].append(timed(fn, True, device, 0, 1, scene.cotangents))
    return {label: (statistics.median(f), statistics.median(fb)) for label, (f, fb) in samples.items()}


def raster_scene_rows(scene, target, vs, device, rounds):
    """Rows of every knob point on one scene, errors against ``target`` (described by ``vs``)."""
    points = raster_points()
    times = median_times(scene, points, device, rounds)
    rows = []
    for label, options in points:
        measured = render_for_errors(scene, options)
        rows.append({"section": "raster", "scene": scene.name, "point": label, "fwd_ms": times[label][0],
                     "fwd_bwd_ms": times[label][1], **errors(measured, target), "vs": vs,
                     "intersections": measured["intersections"]})
    return rows


def raster_section(args):
    """The rasterizer's knobs on the small (reference) scene and the timing scene.

    ``args``: kind (a ``make_scene`` kind), small and timing ((N, width, height) each), large (the
    timing scene is 1M Gaussians at 1920×1080 instead), device, rounds.
    """
    small = make_raster_scene(args.kind, *args.small, args.device)
    print(f"float64 reference of {small.name} (dense, CPU)...", flush=True)
    rows = raster_scene_rows(small, render_reference(small), "float64 reference", args.device, args.rounds)
    big = make_raster_scene(args.kind, *((1_000_000, 1920, 1080) if args.large else args.timing), args.device)
    print(f"timing scene {big.name}...", flush=True)
    rows += raster_scene_rows(big, render_for_errors(big), "default float32", args.device, args.rounds)
    return rows


# The model and training sections: Scaffold-GS trained on the built-in synthetic scene. ``args``:
# iterations, width, height, train_views, test_views, points, device, rounds.

# One knob at a time away from HeadsConfig's defaults (k = 10, feat_dim = 32, no feature bank):
# label -> HeadsConfig overrides. feat_dim is also the hidden width of Scaffold-GS's MLPs.
MODEL_KNOBS = {"default": {}, "k=5": {"n_offsets": 5}, "k=20": {"n_offsets": 20},
               "feat_dim=16": {"feat_dim": 16}, "feat_dim=64": {"feat_dim": 64},
               "feat_bank=on": {"feature_bank": True}}

# Fractions of --iterations at which the training section evaluates.
TRAINING_FRACTIONS = (0.1, 0.25, 0.5, 1.0)


def synthetic_scene(args):
    """The built-in synthetic scene at --width × --height (what ``securegs train`` trains on)."""
    from .data import make_synthetic_scene

    return make_synthetic_scene(width=args.width, height=args.height, n_train=args.train_views,
                                n_test=args.test_views, n_points=args.points)


def scene_label(args):
    return f"synthetic {args.width}×{args.height}, {args.iterations} it"


def make_trainer(scene, args, **heads):
    """ScaffoldTrainer with the rasterizer options for the device (``RasterOptions.for_device``) and
    ``heads`` (HeadsConfig fields) set."""
    from .config import HeadsConfig, TrainConfig
    from .train import ScaffoldTrainer

    config = TrainConfig(iterations=args.iterations, heads=HeadsConfig(**heads),
                         raster=RasterOptions.for_device(args.device))
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
    feat = trainer.model.anchors.feat
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
# Accuracy against time: outputs


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
    save_figure(fig, path, dpi=120)


def write(rows, out, title):
    """accuracy_vs_time.csv, .md and .png (``plot``; needs matplotlib) in ``out``; returns the markdown."""
    os.makedirs(out, exist_ok=True)
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns(rows))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(os.path.join(out, "accuracy_vs_time.csv"), lambda f: f.write(text.getvalue().encode()))
    table = markdown(rows, title)
    atomic_write(os.path.join(out, "accuracy_vs_time.md"), lambda f: f.write(table.encode()))
    plot(rows, os.path.join(out, "accuracy_vs_time.png"))
    return table

