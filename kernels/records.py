"""Packed per-Gaussian records: what the blending kernels gather for each Gaussian of a batch.

The projection writes a visible Gaussian's row (``projection_kernel`` with ``record``)
beside its per-field outputs; the blending kernels gather a batch's rows with one indexed load
instead of one per field (see ``blend``).
"""
from typing import Any

import warp as wp

# Element type of the colour table the kernels read, by ``color_storage`` name.
COLOR_STORAGES = {"float32": wp.float32, "float16": wp.float16}

# A record's float32 words: x, y, conic a, b, c, opacity, depth, the half-widths of its blending box
# (``blend_box``; in the RGB record they fill what was padding), then its colours when they are
# float32, padded to a multiple of 4 words so that rows are 16-byte aligned. float16 colours stay in
# their own [N, C] table (a second indexed load per batch): widened into the float32 record they
# would take twice the bytes, which float16 storage exists to save.
R_XY, R_CONIC, R_OPACITY, R_DEPTH, R_BOX, R_COLOR = 0, 2, 5, 6, 7, 9

# Bound on the relative error of the blending kernels' float32 sigma per unit of the conic's
# condition number κ: the terms of ½(a·dx² + c·dy²) + b·dx·dy add up to at most 2κ·sigma, each
# rounded once or twice (3 ε ≈ 1.8e-7 a unit of sigma); four times that for margin.
_SIGMA_ERROR_PER_KAPPA = 1.5e-6
# Absolute slack on a threshold in sigma units where the blending kernels evaluate sigma and exp in
# float32 (exp's few-ulp error, pixel-centre rounding): the binning's ellipse test and the blending
# box both widen by it. Then the box's half-widths' slack (pixels: rounding of the pixel offsets and
# of the box test), plus the offsets' own ulp at large coordinates.
SIGMA_SLACK = 1.0e-3
_BOX_SLACK_PX = 1.0e-2
_BOX_SLACK_REL = 1.0e-6
# Half-width that no test rejects: the box of a Gaussian too ill-conditioned to bound.
NO_BOX = 1.0e30


def colors_in_record(color_storage: str) -> bool:
    """Whether the packed record holds the colours (float32 storage) or they stay in their table."""
    return color_storage == "float32"


def record_width(channels: int, color_storage: str) -> int:
    """float32 words per packed record: ``R_COLOR`` (+ C colours when in the record), rounded up to 4."""
    words = R_COLOR + (channels if colors_in_record(color_storage) else 0)
    return (words + 3) // 4 * 4


@wp.func
def record_word(src: Any, row: int, k: int):
    """Word ``k`` of row ``row`` of packed records: the [N, P / 4] vec4 table or a batch of it in
    shared memory. vec4 columns make the batch gather 16 bytes a load instead of 4."""
    return src[row, k // 4][k % 4]


@wp.func
def record_geometry(src: Any, row: int):
    """(mean2d, conic, opacity) of row ``row`` of packed records (see ``record_word``)."""
    return (wp.vec2(record_word(src, row, R_XY), record_word(src, row, R_XY + 1)),
            wp.vec3(record_word(src, row, R_CONIC), record_word(src, row, R_CONIC + 1),
                    record_word(src, row, R_CONIC + 2)),
            record_word(src, row, R_OPACITY))


@wp.func
def blend_box(xy: wp.vec2, conic: wp.vec3, opacity: float, alpha_min: float) -> wp.vec2:
    """Half-widths (x, y) of a box around ``xy`` outside which no pixel centre passes the blending
    kernels' test o·e^(−σ) >= alpha_min as they evaluate it in float32: the axis-aligned box of the
    ellipse σ = ln(o / alpha_min) of the conic as stored, its threshold widened by the rounding error
    of σ (which grows with the conic's condition number), and a little more in pixels. The blending
    backward skips a Gaussian for a whole warp whose pixels all lie outside it (same gradients).
    ``NO_BOX`` where the rounding cannot be bounded; negative where no pixel can pass (o below
    alpha_min by more than the slack)."""
    a = wp.float64(conic[0])
    b = wp.float64(conic[1])
    c = wp.float64(conic[2])
    det = a * c - b * b
    half_trace = wp.float64(0.5) * (a + c)
    root = wp.sqrt(wp.max(wp.float64(0.25) * (a - c) * (a - c) + b * b, wp.float64(0.0)))
    low = half_trace - root
    # The threshold with its slack: below 0 no pixel passes (the slack also covers an exp that
    # rounds e^0 above 1 for an opacity a rounding error below alpha_min).
    threshold = wp.log(wp.float64(opacity) / wp.float64(alpha_min)) + wp.float64(SIGMA_SLACK)
    box = wp.vec2(NO_BOX, NO_BOX)
    if threshold < wp.float64(0.0):
        box = wp.vec2(-NO_BOX, -NO_BOX)
    elif det > wp.float64(0.0) and low > wp.float64(0.0):
        error = wp.float64(_SIGMA_ERROR_PER_KAPPA) * (half_trace + root) / low
        if error < wp.float64(0.5):
            t = threshold / (wp.float64(1.0) - error)
            slack = wp.float64(_BOX_SLACK_PX) + wp.float64(_BOX_SLACK_REL) * wp.float64(
                wp.abs(xy[0]) + wp.abs(xy[1]))
            grow = wp.float64(1.0) + wp.float64(_BOX_SLACK_REL)
            box = wp.vec2(wp.float32(wp.sqrt(wp.float64(2.0) * t * c / det) * grow + slack),
                          wp.float32(wp.sqrt(wp.float64(2.0) * t * a / det) * grow + slack))
    return box


@wp.func
def outside_box(src: Any, row: int, x_lo: float, x_hi: float, y_lo: float, y_hi: float) -> bool:
    """Whether row ``row``'s blending box (``blend_box``) misses the pixel centres in [x_lo, x_hi] ×
    [y_lo, y_hi] (see ``record_word`` for ``src``)."""
    x = record_word(src, row, R_XY)
    y = record_word(src, row, R_XY + 1)
    hx = record_word(src, row, R_BOX)
    hy = record_word(src, row, R_BOX + 1)
    return x + hx < x_lo or x - hx > x_hi or y + hy < y_lo or y - hy > y_hi
