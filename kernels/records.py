"""Packed per-Gaussian records: what the blending kernels gather for each Gaussian of a batch.

The projection writes a visible Gaussian's row (``projection_kernel`` with ``record``)
beside its per-field outputs; the blending kernels gather a batch's rows with one indexed load
instead of one per field (see ``blend``).
"""
from typing import Any

import warp as wp

# Element type of the colour table the kernels read, by ``color_storage`` name.
COLOR_STORAGES = {"float32": wp.float32, "float16": wp.float16}

# A record's float32 words: x, y, conic a, b, c, opacity, depth, then its colours when they are
# float32, padded to a multiple of 4 words so that rows are 16-byte aligned. float16 colours stay in
# their own [N, C] table (a second indexed load per batch): widened into the float32 record they
# would take twice the bytes, which float16 storage exists to save.
R_XY, R_CONIC, R_OPACITY, R_DEPTH, R_COLOR = 0, 2, 5, 6, 7


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
