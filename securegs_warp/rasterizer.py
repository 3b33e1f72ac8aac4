"""``rasterize``: the differentiable Warp rasterizer as a torch autograd op.

One ``wp.Tape`` records a whole render: the projection kernel (Warp's generated adjoint) and the
blending kernel, whose hand-written adjoint is put on the same tape with ``Tape.record_func``.
Torch tensors are shared with Warp through ``wp.from_torch`` (no copies); Warp runs on the torch
device of the inputs and on torch's current stream, so the CPU and CUDA share one code path.
"""
from __future__ import annotations

import dataclasses
import math

import torch
import warp as wp

from .kernels import binning
from .kernels.blend import COLOR_STORAGES, CPU_BATCH, batch_size, blend_kernels
from .kernels.projection import RADIUS_RULES, projection_kernel

DEPTH_MODES = (None, "accumulated", "expected")
# Which tiles a Gaussian is binned to: every tile of its radius rectangle (gsplat 1.5), or only those
# its ellipse at the alpha threshold reaches (same image, fewer intersections to sort and blend).
TILE_OVERLAPS = ("ellipse", "rectangle")


@dataclasses.dataclass(frozen=True)
class RasterOptions:
    """Everything that changes what or how ``rasterize`` computes. Defaults are gsplat 1.5's.

    Flags (antialiased, radius_rule, tile_size, depth on/off, channel count, fast_math,
    color_storage) select compiled kernel variants, so an effect that is off costs nothing; the
    numbers are run-time kernel arguments.

    Accuracy for time (scripts/accuracy_vs_time.py measures both):
    fast_math: projection and blending compiled with Warp's fast math (CUDA only; Warp 1.19's
        CPU compiler ignores the option, so on the CPU it changes nothing).
    color_storage: "float16" blends from a float16 copy of ``colors`` made once per render (half
        the bytes per colour read, for wide feature fields on the GPU; on the CPU each read pays a
        conversion). The image error is at most the colours' float16 rounding (≤ 2⁻¹¹·max|colour|,
        2⁻¹² for colours in [0, 1]); colour gradients are still float32. Colours beyond ±65504
        would become inf there and raise ValueError.
    """

    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    radius_clip: float = 0.0
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.999
    transmittance_min: float = 1e-4
    tile_size: int = 16
    antialiased: bool = False
    radius_rule: str = "opacity_aware"
    render_depth: str | None = None
    fast_math: bool = False
    color_storage: str = "float32"
    # "ellipse": bin a Gaussian only to the tiles of its radius rectangle where opacity·e^(−σ) reaches
    # alpha_min at some pixel centre (an exact ellipse–rectangle test; kernels/binning.py). The image
    # is the same as "rectangle"'s (gsplat's binning): the dropped tiles receive no contribution.
    tile_overlap: str = "ellipse"
    # CUDA launch shape only (results do not depend on it): threads per block of the forward and
    # backward blending kernels; a block owns that many pixels of a tile and shares each batch of
    # Gaussians between them. 256 because backward blocks of 256 measured faster than blocks of 32
    # (docs/results.md, "Rasterizer speed against gsplat"; scripts/bench_rasterizer.py --variant
    # b32:backward_block=32 compares them).
    forward_block: int = 256
    backward_block: int = 256

    def __post_init__(self):
        if self.tile_size not in (8, 16, 32):
            raise ValueError(f"tile_size must be 8, 16 or 32, got {self.tile_size}")
        if self.radius_rule not in RADIUS_RULES:
            raise ValueError(f"radius_rule must be one of {RADIUS_RULES}, got {self.radius_rule!r}")
        if self.color_storage not in COLOR_STORAGES:
            raise ValueError(f"color_storage must be one of {tuple(COLOR_STORAGES)}, got {self.color_storage!r}")
        if self.tile_overlap not in TILE_OVERLAPS:
            raise ValueError(f"tile_overlap must be one of {TILE_OVERLAPS}, got {self.tile_overlap!r}")
        if self.render_depth not in DEPTH_MODES:
            raise ValueError(f"render_depth must be one of {DEPTH_MODES}, got {self.render_depth!r}")
        if not 0.0 < self.near_plane < self.far_plane:
            raise ValueError(f"need 0 < near_plane < far_plane, got {self.near_plane}, {self.far_plane}")
        if not 0.0 < self.alpha_min <= self.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min <= alpha_max < 1, got {self.alpha_min}, {self.alpha_max}")
        if not 0.0 <= self.transmittance_min < 1.0:
            raise ValueError(f"need 0 <= transmittance_min < 1, got {self.transmittance_min}")
        if self.eps2d < 0.0:
            raise ValueError(f"eps2d must be >= 0, got {self.eps2d}")
        for name in ("forward_block", "backward_block"):
            b = getattr(self, name)
            # At least one full warp: the backward reduces gradients with 32-lane shuffles.
            if b < 32 or b & (b - 1) or b > 1024:
                raise ValueError(f"{name} must be a power of two in [32, 1024], got {b}")

    @classmethod
    def for_device(cls, device: torch.device | str, **fields) -> RasterOptions:
        """Options for rendering on ``device``: the given ``fields``, and the tile size that suits it
        unless ``fields`` names one.

        The tile is 8 on the CPU, where each pixel's thread walks its tile's list of Gaussians and
        smaller tiles give shorter lists (faster there), and 16 on CUDA (gsplat's default). This is
        the one place the rule is written. Raises ValueError as ``RasterOptions`` does, and for an
        unknown field (``UnknownOptionError``, naming it and listing the valid ones).

        >>> RasterOptions.for_device("cpu").tile_size, RasterOptions.for_device("cuda").tile_size
        (8, 16)
        """
        check_option_names(fields)
        fields.setdefault("tile_size", 8 if torch.device(device).type == "cpu" else 16)
        return cls(**fields)

    def block(self, threads: int) -> int:
        """Block size for a blending kernel: at most one tile, a divisor of its pixel count."""
        return min(threads, self.tile_size * self.tile_size)


class UnknownOptionError(ValueError, TypeError):
    """A keyword that is not a ``RasterOptions`` field. A ValueError like every other bad option;
    also a TypeError, which is what an unexpected keyword argument raises in Python."""


def check_option_names(names) -> None:
    """Raise ``UnknownOptionError`` naming every one of ``names`` that is not a ``RasterOptions``
    field, and listing the fields."""
    valid = [f.name for f in dataclasses.fields(RasterOptions)]
    unknown = [name for name in names if name not in valid]
    if unknown:
        raise UnknownOptionError(f"unknown rasterize option(s) {', '.join(map(repr, unknown))}; "
                                 f"valid RasterOptions fields: {', '.join(valid)}")


def resolve_options(options: RasterOptions | None = None, **overrides) -> RasterOptions:
    """``options`` (default ``RasterOptions()``) with ``overrides`` replacing its fields.

    Raises:
        UnknownOptionError (a ValueError): an override that is not a field, named with the valid ones.
        ValueError: a field value ``RasterOptions`` refuses.
    """
    if options is not None and not isinstance(options, RasterOptions):
        raise ValueError(f"options must be a RasterOptions, got {type(options).__name__}")
    check_option_names(overrides)
    if options is None:
        return RasterOptions(**overrides)
    return dataclasses.replace(options, **overrides) if overrides else options


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    options: RasterOptions | None = None,
    **overrides,
):
    """Render N 3D Gaussians from one pinhole camera, differentiably.

    ``rasterize(..., options=RasterOptions(tile_size=8))`` and ``rasterize(..., tile_size=8)`` are the
    same render; given both, the keywords replace those fields of ``options``
    (``dataclasses.replace(options, **overrides)``).

    Args:
        means: [N, 3] centres in world space.
        quats: [N, 4] rotations, w first; need not be normalised.
        scales: [N, 3] linear (not log) standard deviations along the rotated axes.
        opacities: [N] in [0, 1].
        colors: [N, C] per-Gaussian values, any C >= 1 (3 for RGB, 16+ for feature fields).
        viewmat: [4, 4] world-to-camera, OpenCV axes (x right, y down, z forward).
        K: [3, 3] pinhole intrinsics (fx, fy, cx, cy used).
        width, height: image size in pixels.
        background: [C] colour behind the Gaussians, or None for zeros.
        options: a ``RasterOptions``, or None for its defaults (gsplat 1.5's; see
            ``RasterOptions.for_device`` for the tile size that suits a device).
        **overrides: fields of ``RasterOptions`` (near_plane, far_plane, eps2d, radius_clip,
            alpha_min, alpha_max, transmittance_min, tile_size, antialiased, radius_rule,
            render_depth=None | "accumulated" | "expected", fast_math, color_storage="float32" |
            "float16", tile_overlap="ellipse" | "rectangle", forward_block, backward_block), replacing
            those of ``options``.

    Returns:
        image [H, W, C], alpha [H, W, 1], info: dict with
        ``radii`` [N, 2] int32 (0: culled), ``means2d`` [N, 2], ``conics`` [N, 3], ``depths`` [N],
        ``opacities`` [N] (after antialiasing compensation), ``n_intersections``, ``tile_size``,
        ``width``, ``height``, ``depth`` [H, W, 1] when asked, and ``means2d_grad`` [N, 2], which the
        backward pass fills with dL/d means2d (pixels) for densification statistics.

    Raises:
        ValueError: a tensor with the wrong shape, a non-finite value (naming the tensor), a bad
            option value, an unknown option keyword (``UnknownOptionError``, which names it and
            lists the valid fields; also a TypeError), or a non-positive image size.
    """
    opts = resolve_options(options, **overrides)
    named = _validated(means, quats, scales, opacities, colors, viewmat, K, width, height, background)
    means, quats, scales, opacities, colors, viewmat, K, background = named.values()
    # The table the blending kernels read: a float16 copy made once per render, or colors itself.
    color_table = colors.to(torch.float16) if opts.color_storage == "float16" else colors
    checked = dict(named)
    if color_table is not colors:
        checked["colors (as float16: |value| > 65504)"] = color_table
    # Finiteness is checked on the device and read back with the intersection count (one sync):
    # one fused max-|value| reduction over all inputs (NaN and inf propagate through it; empty
    # tensors have no maximum and are finite).
    nonempty = [t for t in checked.values() if t.numel()]
    finite = torch.ones(len(checked), dtype=torch.bool, device=means.device)
    if nonempty:
        finite[[i for i, t in enumerate(checked.values()) if t.numel()]] = \
            torch.stack(torch._foreach_norm(nonempty, math.inf)).isfinite()
    n = means.shape[0]
    info = {
        "means2d_grad": torch.zeros(n, 2, device=means.device, dtype=torch.float32),
        "tile_size": opts.tile_size,
        "width": int(width),
        "height": int(height),
    }
    camera = (viewmat.detach().reshape(16), K.detach().reshape(9))
    image, alpha, depth, radii, means2d, conics, depths, opac, n_isect = _Rasterize.apply(
        means, quats, scales, opacities, colors, color_table, background, camera, int(width), int(height), opts,
        info, (tuple(checked), finite),
    )
    info.update(radii=radii, means2d=means2d, conics=conics, depths=depths, opacities=opac, n_intersections=n_isect)
    if opts.render_depth == "accumulated":
        info["depth"] = depth
    elif opts.render_depth == "expected":
        info["depth"] = depth / alpha.clamp_min(1e-10)
    return image, alpha, info


def _validated(means, quats, scales, opacities, colors, viewmat, K, width, height, background):
    """Check types, shapes and devices; return name → float32 contiguous tensor (background filled)."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
             "viewmat": viewmat, "K": K}
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if not (t.dtype.is_floating_point):
            raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    expected = {"quats": (n, 4), "scales": (n, 3), "opacities": (n,), "viewmat": (4, 4), "K": (3, 3)}
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(named[name].shape)}")
    if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"colors must be [N, C] with N={n} and C >= 1, got {list(colors.shape)}")
    c = colors.shape[1]
    if background is None:
        background = torch.zeros(c, device=means.device, dtype=torch.float32)
    elif not isinstance(background, torch.Tensor) or tuple(background.shape) != (c,):
        raise ValueError(f"background must be a tensor of shape [{c}] (one value per colour channel)")
    named["background"] = background
    for name, t in named.items():
        if t.device != means.device:
            raise ValueError(f"{name} is on {t.device} but means is on {means.device}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"width and height must be >= 1, got {width}x{height}")
    return {name: t.float().contiguous() for name, t in named.items()}


def _wp(t: torch.Tensor, dtype, grad: bool = False, retain_grad: bool = False):
    """Warp view of a contiguous torch tensor; with ``grad``, a zeroed torch-backed gradient too.

    ``retain_grad`` keeps the gradient of an intermediate array after the tape has consumed it.
    """
    if grad:
        return wp.from_torch(t, dtype=dtype, requires_grad=True, grad=torch.zeros_like(t), retain_grad=retain_grad)
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, color_table, background, camera, width, height, opts,
                info, finite):
        wp.init()  # idempotent; Warp must be up before its devices can be named
        device = wp.device_from_torch(means.device)
        n, c = colors.shape
        tdev = means.device
        f32 = dict(device=tdev, dtype=torch.float32)
        with_depth = opts.render_depth is not None
        ts = opts.tile_size
        tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)

        with wp.ScopedDevice(device), wp.ScopedStream(_stream(means.device)):
            w_means = _wp(means, wp.vec3, grad=True)
            w_quats = _wp(quats, wp.vec4, grad=True)
            w_scales = _wp(scales, wp.vec3, grad=True)
            w_opac = _wp(opacities, wp.float32, grad=True)
            # Colours only reach the hand-written blend adjoint, which writes their float32 gradient
            # here whatever the table's storage type.
            w_colors = _wp(color_table, COLOR_STORAGES[opts.color_storage])
            w_colors_grad = _wp(torch.zeros_like(colors), wp.float32)
            w_bg = _wp(background, wp.float32, grad=True)

            means2d = torch.zeros(n, 2, **f32)
            conics = torch.zeros(n, 3, **f32)
            depths = torch.zeros(n, **f32)
            opac_out = torch.zeros(n, **f32)
            radii = torch.zeros(n, 2, device=tdev, dtype=torch.int32)
            w_means2d = _wp(means2d, wp.vec2, grad=True, retain_grad=True)  # densification statistics
            w_conics = _wp(conics, wp.vec3, grad=True)
            w_depths = _wp(depths, wp.float32, grad=True)
            w_opac_out = _wp(opac_out, wp.float32, grad=True)
            w_radii = _wp(radii, wp.vec2i)

            w_viewmat, w_K = (_wp(t, wp.float32) for t in camera)
            tape = wp.Tape()
            with tape:
                wp.launch(
                    projection_kernel(opts.antialiased, opts.radius_rule, opts.fast_math),
                    dim=n,
                    inputs=[w_means, w_quats, w_scales, w_opac, w_viewmat, w_K, width, height,
                            opts.near_plane, opts.far_plane, opts.eps2d, opts.alpha_min, opts.radius_clip],
                    outputs=[w_means2d, w_conics, w_depths, w_radii, w_opac_out],
                )

            ranges, sorted_ids, n_isect = _bin(w_means2d, w_radii, w_conics, w_opac_out, depths, opts, tiles_x,
                                               tiles_y, finite)

            image = torch.empty(height, width, c, **f32)
            alpha = torch.empty(height, width, 1, **f32)
            depth_img = torch.zeros(height, width, 1, **f32)
            transmittance = torch.empty(height, width, **f32)
            last = torch.empty(height, width, device=tdev, dtype=torch.int32)
            w_image = _wp(image, wp.float32, grad=True)
            w_alpha = _wp(alpha, wp.float32, grad=True)
            w_depth_img = _wp(depth_img, wp.float32, grad=True)
            w_trans = _wp(transmittance, wp.float32)
            w_last = _wp(last, wp.int32)

            cooperative = not (device.is_cpu and not wp.config.enable_cpu_blocks)
            fwd_block = opts.block(opts.forward_block)
            batch = batch_size(c, fwd_block, with_depth, opts.color_storage) if cooperative else CPU_BATCH
            fwd, bwd = blend_kernels(c, ts, with_depth, batch, cooperative, opts.color_storage, opts.fast_math)
            common = [ranges, sorted_ids, w_means2d, w_conics, w_opac_out, w_colors, w_depths, w_bg,
                      width, height, tiles_x, opts.alpha_min, opts.alpha_max]
            lanes = ts * ts  # one thread per pixel of a tile
            wp.launch(fwd, dim=(tiles_x * tiles_y, lanes), block_dim=fwd_block,
                      inputs=common + [opts.transmittance_min],
                      outputs=[w_image, w_alpha, w_depth_img, w_trans, w_last])

            def blend_adjoint():
                wp.launch(bwd, dim=(tiles_x * tiles_y, lanes), block_dim=opts.block(opts.backward_block),
                          inputs=common + [w_trans, w_last, w_image.grad, w_alpha.grad, w_depth_img.grad],
                          outputs=[w_means2d.grad, w_conics.grad, w_opac_out.grad, w_colors_grad,
                                   w_depths.grad, w_bg.grad])

            tape.record_func(blend_adjoint, arrays=[w_image, w_alpha, w_depth_img])

        ctx.tape = tape
        ctx.device = means.device
        ctx.info = info
        ctx.grads = (w_means.grad, w_quats.grad, w_scales.grad, w_opac.grad, w_colors_grad, w_bg.grad)
        ctx.out_grads = (w_image.grad, w_alpha.grad, w_depth_img.grad)
        ctx.means2d_grad = w_means2d.grad
        ctx.mark_non_differentiable(radii, means2d, conics, depths, opac_out)
        return image, alpha, depth_img, radii, means2d, conics, depths, opac_out, n_isect

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth, *_):
        with wp.ScopedDevice(wp.device_from_torch(ctx.device)), wp.ScopedStream(_stream(ctx.device)):
            for w_grad, g in zip(ctx.out_grads, (g_image, g_alpha, g_depth)):
                if g is not None:
                    wp.to_torch(w_grad).copy_(g)
            ctx.tape.backward()
        ctx.info["means2d_grad"] += wp.to_torch(ctx.means2d_grad)
        grads = [wp.to_torch(g) for g in ctx.grads]
        ctx.tape = None  # release the Warp arrays
        # grads for means, quats, scales, opacities, colors (not color_table), background; none beyond.
        return (*grads[:5], None, grads[5], None, None, None, None, None, None)


def _stream(device: torch.device):
    return wp.stream_from_torch(device) if device.type == "cuda" else None


def _bin(w_means2d, w_radii, w_conics, w_opac, depths, opts, tiles_x, tiles_y, finite):
    """Sorted (tile, depth) intersections → per-tile ranges [T, 2] and Gaussian ids (Warp arrays).

    Tiles are those of each Gaussian's radius rectangle, or of them only those its ellipse reaches
    (``opts.tile_overlap``).

    ``finite`` = (input names, [inputs] bool device tensor): read back with the intersection count
    in the render's single host synchronisation; a non-finite input raises ValueError naming it.
    """
    n = depths.shape[0]
    n_tiles = tiles_x * tiles_y
    tile_size = opts.tile_size
    overlap = [w_conics, w_opac, opts.alpha_min, int(opts.tile_overlap == "ellipse")]
    ranges = wp.zeros((n_tiles, 2), dtype=wp.int32)
    counts = wp.empty(n, dtype=wp.int64)
    wp.launch(binning.count_tiles, dim=n, inputs=[w_means2d, w_radii, *overlap, tile_size, tiles_x, tiles_y],
              outputs=[counts])
    ends = wp.empty(n, dtype=wp.int64)
    names, ok = finite
    host = [0] + ok.tolist() if n == 0 else None
    if n > 0:
        wp.utils.array_scan(counts, ends, inclusive=True)
        host = torch.cat([wp.to_torch(ends)[-1:], ok.long()]).tolist()
    bad = [name for name, flag in zip(names, host[1:]) if not flag]
    if bad:
        raise ValueError(f"non-finite values (NaN or inf) in: {', '.join(bad)}")
    n_isect = int(host[0])
    if n_isect >= 2**31 - 1:
        raise ValueError(f"{n_isect} tile intersections exceed the sort's int32 index range")
    # radix_sort_pairs needs room for 2x the pairs (its scratch space); keep at least one slot.
    keys = wp.empty(max(2 * n_isect, 2), dtype=wp.int64)
    values = wp.empty(max(2 * n_isect, 2), dtype=wp.int32)
    if n_isect > 0:
        depth_bits = wp.from_torch(depths.view(torch.int32), dtype=wp.int32)
        wp.launch(binning.emit_intersections, dim=n,
                  inputs=[w_means2d, w_radii, *overlap, depth_bits, counts, ends, tile_size, tiles_x, tiles_y],
                  outputs=[keys, values])
        tile_bits = max(1, int(n_tiles - 1).bit_length())
        wp.utils.radix_sort_pairs(keys, values, n_isect, end_bit=32 + tile_bits)
        wp.launch(binning.tile_ranges, dim=n_isect, inputs=[keys, n_isect], outputs=[ranges])
    return ranges, values, n_isect
