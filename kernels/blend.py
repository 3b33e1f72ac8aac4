"""Front-to-back alpha blending over each tile's depth-sorted Gaussians, and its adjoint.

Launch layout: ``dim=(n_tiles, tile_size²)``, ``block_dim=tile_size²``: one thread per pixel of a
tile (the backward's threads may walk several pixels each: ``backward_pixels``). On CUDA a block is
a tile: each batch of Gaussians is gathered once into shared memory (``tile_load_indexed``) and
read by every pixel, and the block stops when all its pixels are done.
On the CPU ``block_dim`` resolves to 1: each thread is its own block, gathers the batch itself and
the block-wide votes and sums reduce over one thread — the same code, correct for both.

Warp's tape cannot differentiate this loop (dynamic trip count, early exit, multiplicative
transmittance), so ``backward`` is written by hand, gsplat style: it walks each pixel's list back
to front, recovering the transmittance from the final one. A Gaussian's gradient is summed over
the pixels of a CUDA warp with register shuffles (skipped when no lane touched it) and added to
global memory one value a lane (``gradient_scatter``), into one [N, 6 + C (+1)] table that a second
kernel unpacks into the per-field gradients: a block-wide reduction per Gaussian costs several
times more, one lane adding every value serialises the atomics, and summing a tile's warps in
shared memory first (one global add a Gaussian a batch) measured no faster (docs/results.md,
"Gradient sums in shared memory").

Per-pixel rule (gsplat 1.5): centre at +0.5; σ = ½(a·dx² + c·dy²) + b·dx·dy, skipped if σ < 0;
α = min(alpha_max, o·e^{−σ}), skipped if α < alpha_min; stop *before* a Gaussian that would bring
the transmittance to ≤ t_min; colour = Σ cᵢαᵢTᵢ + T·background.

Accuracy-for-time variants (compile-time, see ``blend_kernels``): colours read from a float16 table
(half the bytes per Gaussian in global and shared memory; arithmetic stays float32 and the colour
gradients are written in float32), and Warp's fast math.

Packed records (``blend_kernels(..., packed=True)``, written by the projection; the layout is in
``kernels/records.py``): each batch is gathered with one ``tile_load_indexed`` of a per-Gaussian
row instead of one per field. In Warp 1.19 each indexed load into shared memory is a register
gather, a store and a block barrier (and, reloaded in a loop, one more barrier before the store),
so the per-field gathers serialise four or five global-memory latencies and 10 or 12 barriers per
batch; the record costs one latency, and its gather (``tile_assign`` into tiles made once) only
the barriers it needs: 2 in the forward, 3 in the backward.
"""
import functools
from typing import Any

import warp as wp

from .records import (COLOR_STORAGES, R_COLOR, R_DEPTH, colors_in_record, outside_box, record_geometry, record_width,
                      record_word)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffff, flag) != 0;
#else
    return flag;
#endif
""")
def warp_any(flag: bool) -> bool:
    """True if any lane of the warp has ``flag`` (CPU: the thread's own flag)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    for (int offset = 16; offset > 0; offset >>= 1) {
        int other = __shfl_xor_sync(0xffffffff, x, offset);
        x = other > x ? other : x;
    }
#endif
    return x;
""")
def warp_max(x: int) -> int:
    """Largest value over the 32 lanes of a CUDA warp; on the CPU a thread is its own warp."""
    ...


@wp.func_native("""
    WP_TILE_SYNC();
""")
def block_barrier():
    """Wait for every thread of the block (CUDA ``__syncthreads``; Warp's CPU blocks likewise)."""
    ...


@wp.func
def warp_band(tile_x0: int, tile_y0: int, tile_size: int, lane: int, pixels: int, lanes: int) -> wp.vec4:
    """(x_lo, x_hi, y_lo, y_hi): the pixel centres of the ``lanes`` consecutive threads (a CUDA warp:
    32; a CPU thread, its own warp: 1) that hold thread ``lane`` of a tile whose top-left pixel is
    (tile_x0, tile_y0), when thread t walks ``pixels`` rows from row (t // tile_size)·pixels of
    column t % tile_size. 32 lanes span whole rows of a tile of 8, 16 or 32."""
    w0 = lane - lane % lanes
    x0 = tile_x0
    x1 = tile_x0 + tile_size - 1
    if lanes < tile_size:
        x0 = tile_x0 + w0 % tile_size
        x1 = x0 + lanes - 1
    return wp.vec4(float(x0) + 0.5, float(x1) + 0.5, float(tile_y0 + (w0 // tile_size) * pixels) + 0.5,
                   float(tile_y0 + ((w0 + lanes - 1) // tile_size) * pixels + pixels) - 0.5)


# Gradient vector layout per Gaussian: [d mean2d (2), d conic (3), d opacity (1), d colour (C), d depth],
# which is also the row layout of the backward's [N, gradient_width] output.
_XY, _CONIC, _OPACITY, _COLOR = 0, 2, 5, 6


def gradient_width(channels: int, with_depth: bool) -> int:
    """Words of one Gaussian's row in the backward's gradient table (see ``_XY`` .. ``_COLOR``)."""
    return _COLOR + channels + int(with_depth)


def _scatter_chunk(c0: int, n: int) -> str:
    """CUDA source summing values ``g[c0 .. c0 + n - 1]`` (n <= 32) over a warp and adding each sum
    to ``grad[gid, c0 + k]`` from a lane of its own.

    A transposed butterfly: at each shuffle distance a lane keeps half of its values and sends the
    other half to its partner, which keeps the other half, so the values halve with each step until
    a lane holds one (index ``idx``); the remaining steps are a plain butterfly. m values (m the power
    of two >= n) take m - 1 + 5 - log2(m) shuffles instead of 5·n, and the n sums are added by n lanes
    at once instead of one after the other by one lane."""
    m = 1
    while m < n:
        m *= 2
    lines = ["    {", f"        float v[{m}];"]
    lines += [f"        v[{i}] = {f'g[{c0 + i}]' if i < n else '0.0f'};" for i in range(m)]
    lines.append("        int idx = 0;")
    offset, half = 16, m // 2
    while half >= 1:
        lines += [f"        {{ const bool up = (lane & {offset}) != 0;",
                  f"          #pragma unroll",
                  f"          for (int i = 0; i < {half}; ++i) {{",
                  f"              const float send = up ? v[i] : v[i + {half}];",
                  f"              const float keep = up ? v[i + {half}] : v[i];",
                  f"              v[i] = keep + __shfl_xor_sync(0xffffffff, send, {offset});",
                  f"          }}",
                  f"          if (up) idx += {half}; }}"]
        offset, half = offset // 2, half // 2
    while offset >= 1:
        lines.append(f"        v[0] += __shfl_xor_sync(0xffffffff, v[0], {offset});")
        offset //= 2
    # Lanes that differ only in the plain butterfly's bits hold the same sum: the lowest adds it.
    lines.append(f"        if ((lane & {32 // m - 1}) == 0 && idx < {n}) "
                 f"wp::atomic_add(wp::address(grad, gid, {c0} + idx), v[0]);")
    lines.append("    }")
    return "\n".join(lines)


@functools.lru_cache(maxsize=None)
def gradient_scatter(width: int):
    """``scatter(g, grad, gid)``: add one Gaussian's gradient vector ``g`` [width], summed over the
    32 lanes of a CUDA warp, to row ``gid`` of ``grad`` [N, width] (see ``_scatter_chunk``); every
    lane of the warp must call it. On the CPU a thread is its own warp and adds its own ``g``."""
    chunks = "\n".join(_scatter_chunk(c0, min(32, width - c0)) for c0 in range(0, width, 32))
    snippet = f"""
#if defined(__CUDA_ARCH__)
    const int lane = threadIdx.x & 31;
{chunks}
#else
    for (int k = 0; k < {width}; ++k) wp::atomic_add(wp::address(grad, gid, k), g[k]);
#endif
"""
    Vec = wp.types.vector(length=width, dtype=wp.float32)

    def scatter(g: Vec, grad: wp.array2d(dtype=wp.float32), gid: int):
        ...

    scatter.__name__ = scatter.__qualname__ = f"scatter_gradients_{width}"
    return wp.func_native(snippet)(scatter)


@functools.lru_cache(maxsize=None)
def unpack_gradients_kernel(channels: int, with_depth: bool):
    """Kernel writing the backward's gradient table ``v_gaussians`` [N, gradient_width] into the per-field
    gradients the projection's adjoint and the caller read: v_means2d [N] vec2, v_conics [N] vec3,
    v_opacities [N], v_colors [N, C] and, with depth, v_depths [N] (overwritten, not added to)."""
    C = channels
    DEPTH = int(with_depth)

    def unpack(v_gaussians: wp.array2d(dtype=float), v_means2d: wp.array(dtype=wp.vec2),
               v_conics: wp.array(dtype=wp.vec3), v_opacities: wp.array(dtype=float), v_colors: wp.array2d(dtype=float),
               v_depths: wp.array(dtype=float)):
        i = wp.tid()
        v_means2d[i] = wp.vec2(v_gaussians[i, _XY], v_gaussians[i, _XY + 1])
        v_conics[i] = wp.vec3(v_gaussians[i, _CONIC], v_gaussians[i, _CONIC + 1], v_gaussians[i, _CONIC + 2])
        v_opacities[i] = v_gaussians[i, _OPACITY]
        for c in range(C):
            v_colors[i, c] = v_gaussians[i, _COLOR + c]
        if wp.static(DEPTH == 1):
            v_depths[i] = v_gaussians[i, _COLOR + C]

    unpack.__name__ = unpack.__qualname__ = f"unpack_gradients_c{C}{'_depth' if DEPTH else ''}"
    return wp.kernel(unpack, enable_backward=False, module="unique")


# Upper bound on the shared memory of one batch (bytes), to pick the batch size for wide colours.
_BATCH_SHARED_BYTES = 24 * 1024

# Pixels a thread of the backward blending kernel may walk (``blend_kernels``' backward_pixels).
BACKWARD_PIXELS = (1, 2, 4)


def backward_threads(tile_size: int, pixels: int) -> int:
    """Threads per tile of the backward blending kernel when each walks ``pixels`` pixels."""
    return tile_size * tile_size // pixels


def check_backward_pixels(tile_size: int, pixels: int) -> None:
    """Refuse a pixel count outside BACKWARD_PIXELS, or one that leaves a tile fewer than 32
    threads: the backward's gradient sums are warp shuffles over 32 lanes."""
    if pixels not in BACKWARD_PIXELS or backward_threads(tile_size, pixels) < 32:
        raise ValueError(f"backward_pixels must be one of {BACKWARD_PIXELS} and leave a tile at least 32 "
                         f"threads, got {pixels} with tile_size {tile_size}")


# On the CPU (one thread per block, direct reads) the batch only paces the walk over the list.
CPU_BATCH = 32


def batch_size(channels: int, block: int, with_depth: bool, color_storage: str, packed: bool) -> int:
    """Gaussians gathered per batch: one per thread of the block (at least 32), fewer when the
    feature channels are wide enough to overflow the shared-memory budget (``packed``: the batch
    holds records of ``record_width`` words)."""
    color_bytes = wp.types.type_size_in_bytes(COLOR_STORAGES[color_storage])
    if packed:
        separate = 0 if colors_in_record(color_storage) else color_bytes * channels
        per_gaussian = 4 * (1 + record_width(channels, color_storage)) + separate
    else:
        per_gaussian = 4 * (1 + 2 + 3 + 1 + int(with_depth)) + color_bytes * channels
    b = max(block, 32)
    while b > 32 and b * per_gaussian > _BATCH_SHARED_BYTES:
        b //= 2
    return b


@functools.lru_cache(maxsize=None)
def blend_kernels(channels: int, tile_size: int, with_depth: bool, batch: int, cooperative: bool,
                  color_storage: str, fast_math: bool, warp_walk: bool = False, max_registers: int = 0, *,
                  packed: bool, backward_pixels: int = 1):
    """(forward, backward) kernels specialised for C channels, one tile size, depth on/off and
    ``batch`` Gaussians per step of the list walk (see ``batch_size``; ``CPU_BATCH`` on the CPU).

    ``cooperative``: gather each batch into shared memory once per block (CUDA). Without it each
    thread reads the Gaussians straight from global memory: the CPU's one-thread blocks would
    only pay for copying a batch that no other thread reads.
    ``color_storage``: element type of the ``colors`` [N, C] table the kernels read ("float32" or
    "float16", a key of ``COLOR_STORAGES``); the colour gradient ``v_colors`` is float32 either way.
    ``fast_math``: compile with Warp's ``fast_math`` module option (see ``projection_kernel``).
    ``warp_walk``: in the backward, each warp walks a batch only from the last Gaussian one of its
    own 32 pixels used (gsplat's bound), instead of from the block's: the batches are still gathered
    for the whole block, but a warp whose pixels stopped early skips their tail without evaluating
    it. Same gradients; only the work skipped differs (a CPU thread is its own warp).
    ``max_registers``: registers per thread the CUDA backward may use (``__maxnreg__``; 0: the
    compiler's choice). Fewer registers let more blocks share a multiprocessor, at the risk of
    spilling to local memory; the CPU ignores it.
    ``packed``: read each Gaussian from its row of ``records`` [N, record_width / 4] vec4
    (``kernels/records.py``), gathered with one indexed load per batch, instead of from means2d,
    conics, opacities, depths (and colors when ``colors_in_record``); the kernels take ``records``
    either way (None when not packed) and read the per-field arrays only for what the record lacks.
    ``backward_pixels``: pixels each thread of the backward walks (1, 2 or 4; launched with
    tile_size² / backward_pixels threads a tile, see ``backward_threads``). A thread reads each
    Gaussian once for its pixels and sums their gradients before the warp's shuffles, so P pixels a
    thread divide the shared-memory reads, shuffles and atomics per pixel by P, for more registers.
    """
    if channels < 1:
        raise ValueError(f"channels must be >= 1, got {channels}")
    check_backward_pixels(tile_size, backward_pixels)
    ColorT = COLOR_STORAGES[color_storage]
    C = channels
    TS = tile_size
    B = batch
    COOP = cooperative
    # Threads that share a warp's vote and sums: a CUDA warp; without cooperative batches (the CPU),
    # each thread is its own.
    LANES = 32 if cooperative else 1
    DEPTH = 1 if with_depth else 0
    NG = gradient_width(C, with_depth)
    WARP_WALK = warp_walk
    PACKED = packed
    Q = record_width(C, color_storage) // 4  # vec4 columns of a record
    # Colours read from the record (else from their own table, tile or array).
    REC_COLOR = packed and colors_in_record(color_storage)
    ColorVec = wp.types.vector(length=C, dtype=wp.float32)
    GradVec = wp.types.vector(length=NG, dtype=wp.float32)
    PX = backward_pixels
    PixVec = wp.types.vector(length=PX, dtype=wp.float32)
    PixInt = wp.types.vector(length=PX, dtype=wp.int32)
    PixColor = wp.types.vector(length=PX * C, dtype=wp.float32)
    scatter = gradient_scatter(NG)

    @wp.func
    def gather_records(sorted_ids: wp.array(dtype=wp.int32), records: wp.array2d(dtype=wp.vec4), b0: int,
                       ids: Any, rec: Any):
        """Batch ``b0 .. b0 + B - 1`` of the tile's list into the shared tiles ``ids`` [B] and ``rec``
        [B, Q], with a block barrier after each (the gather reads other threads' ids; every pixel
        reads every record). Unlike a reload with ``storage="shared"``, no barrier before the stores:
        the records are written after the ids' barrier, when every thread is past the previous batch,
        but a caller whose walk reads ``ids`` needs a barrier before the call."""
        wp.tile_assign(ids, wp.tile_load(sorted_ids, shape=(B,), offset=(b0,)), offset=(0,))
        wp.tile_assign(rec, wp.tile_load_indexed(records, ids, shape=(B, Q), offset=(0, 0), axis=0), offset=(0, 0))

    def forward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array2d(dtype=ColorT),
        depths: wp.array(dtype=float),
        records: wp.array2d(dtype=wp.vec4),
        background: wp.array(dtype=float),
        width: int,
        height: int,
        tiles_x: int,
        alpha_min: float,
        alpha_max: float,
        t_min: float,
        out_color: wp.array3d(dtype=float),
        out_alpha: wp.array3d(dtype=float),
        out_depth: wp.array3d(dtype=float),
        out_transmittance: wp.array2d(dtype=float),
        out_last: wp.array2d(dtype=wp.int32),
    ):
        tile, lane = wp.tid()
        ty = tile // tiles_x
        px = (tile - ty * tiles_x) * TS + lane % TS
        py = ty * TS + lane // TS
        inside = px < width and py < height
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        start = ranges[tile, 0]
        end = ranges[tile, 1]

        T = float(1.0)
        acc = ColorVec()
        acc_depth = float(0.0)
        last = int(-1)
        done = not inside
        n_batches = (end - start + B - 1) // B
        if wp.static(PACKED and COOP):
            ids = wp.tile_empty(shape=(B,), dtype=wp.int32, storage="shared")
            rec = wp.tile_empty(shape=(B, Q), dtype=wp.vec4, storage="shared")
        elif wp.static(PACKED):
            rec = records
        for b in range(n_batches):
            b0 = start + b * B
            if wp.static(COOP):
                # Block-wide vote: stop when every pixel of the tile is done.
                n_done = wp.tile_sum(wp.tile(wp.where(done, 1, 0)))
                if wp.tile_extract(n_done, 0) == wp.block_dim():
                    break
            elif done:
                break
            if wp.static(PACKED and COOP):
                # No barrier first: the walk does not read ids, and every gather that did passed its own.
                gather_records(sorted_ids, records, b0, ids, rec)
                if wp.static(not REC_COLOR):
                    col_t = wp.tile_load_indexed(colors, ids, shape=(B, C), offset=(0, 0), axis=0, storage="shared")
            elif wp.static(COOP):
                ids = wp.tile_load(sorted_ids, shape=(B,), offset=(b0,), storage="shared")
                xy_t = wp.tile_load_indexed(means2d, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                cn_t = wp.tile_load_indexed(conics, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                op_t = wp.tile_load_indexed(opacities, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                col_t = wp.tile_load_indexed(colors, ids, shape=(B, C), offset=(0, 0), axis=0, storage="shared")
                if wp.static(DEPTH == 1):
                    dep_t = wp.tile_load_indexed(depths, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
            count = wp.min(B, end - b0)
            if not done:
                for j in range(count):
                    if wp.static(COOP):
                        row = j
                    else:
                        gid = sorted_ids[b0 + j]
                        row = gid
                    if wp.static(PACKED and not COOP):
                        # A thread reading its own batch skips a Gaussian whose blending box misses
                        # its pixel (on CUDA, where a warp shares a batch, this measured slower).
                        if outside_box(rec, row, fx, fx, fy, fy):
                            continue
                    if wp.static(PACKED):
                        xy, cn, op = record_geometry(rec, row)
                    elif wp.static(COOP):
                        xy = xy_t[j]
                        cn = cn_t[j]
                        op = op_t[j]
                    else:
                        xy = means2d[gid]
                        cn = conics[gid]
                        op = opacities[gid]
                    dx = xy[0] - fx
                    dy = xy[1] - fy
                    sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
                    alpha = wp.min(alpha_max, op * wp.exp(-sigma))
                    if sigma >= 0.0 and alpha >= alpha_min:
                        next_t = T * (1.0 - alpha)
                        if next_t <= t_min:
                            done = True
                            break
                        w = alpha * T
                        for c in range(C):
                            # float(): widen a float16 colour (the identity for float32).
                            if wp.static(REC_COLOR):
                                acc[c] = acc[c] + record_word(rec, row, R_COLOR + c) * w
                            elif wp.static(COOP):
                                acc[c] = acc[c] + float(col_t[j, c]) * w
                            else:
                                acc[c] = acc[c] + float(colors[gid, c]) * w
                        if wp.static(DEPTH == 1):
                            if wp.static(PACKED):
                                acc_depth += record_word(rec, row, R_DEPTH) * w
                            elif wp.static(COOP):
                                acc_depth += dep_t[j] * w
                            else:
                                acc_depth += depths[gid] * w
                        T = next_t
                        last = b0 + j
        if inside:
            for c in range(C):
                out_color[py, px, c] = acc[c] + T * background[c]
            out_alpha[py, px, 0] = 1.0 - T
            if wp.static(DEPTH == 1):
                out_depth[py, px, 0] = acc_depth
            out_transmittance[py, px] = T
            out_last[py, px] = last

    def backward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array2d(dtype=ColorT),
        depths: wp.array(dtype=float),
        records: wp.array2d(dtype=wp.vec4),
        background: wp.array(dtype=float),
        width: int,
        height: int,
        tiles_x: int,
        alpha_min: float,
        alpha_max: float,
        transmittance: wp.array2d(dtype=float),
        last_ids: wp.array2d(dtype=wp.int32),
        v_color: wp.array3d(dtype=float),
        v_alpha: wp.array3d(dtype=float),
        v_depth: wp.array3d(dtype=float),
        v_gaussians: wp.array2d(dtype=float),
        v_background: wp.array(dtype=float),
    ):
        # Thread ``lane`` walks the PX pixels of column lane % TS in rows PX·(lane // TS) + p of its
        # tile, so a warp's pixels stay a compact band of whole rows (PX = 1: one pixel a thread).
        tile, lane = wp.tid()
        ty = tile // tiles_x
        px = (tile - ty * tiles_x) * TS + lane % TS
        row0 = ty * TS + (lane // TS) * PX
        fx = float(px) + 0.5
        start = ranges[tile, 0]
        leader = lane % wp.block_dim() == 0
        band = warp_band((tile - ty * tiles_x) * TS, ty * TS, TS, lane, PX, LANES)

        # Per-pixel state, pixel p at [p] (and colour c at [p·C + c]).
        fy = PixVec()
        t_final = PixVec()
        last = PixInt()
        v_img = PixColor()
        v_a_eff = PixVec()
        v_d = PixVec()
        bg_part = ColorVec()
        last_max = int(-1)
        for p in range(PX):
            py = row0 + p
            fy[p] = float(py) + 0.5
            t_final[p] = 1.0
            last[p] = -1
            if px < width and py < height:
                t_final[p] = transmittance[py, px]
                last[p] = last_ids[py, px]
                # Background: d colour / d bg = T_final; through T_final it also lowers d alpha.
                bg_dot = float(0.0)
                for c in range(C):
                    v_img[p * C + c] = v_color[py, px, c]
                    bg_dot += background[c] * v_img[p * C + c]
                    bg_part[c] = bg_part[c] + v_img[p * C + c] * t_final[p]
                v_a_eff[p] = v_alpha[py, px, 0] - bg_dot
                if wp.static(DEPTH == 1):
                    v_d[p] = v_depth[py, px, 0]
            last_max = wp.max(last_max, last[p])
        v_bg = wp.tile_extract(wp.tile_sum(wp.tile(bg_part, preserve_type=True)), 0)
        if leader:
            for c in range(C):
                wp.atomic_add(v_background, c, v_bg[c])

        # Walk from the last Gaussian any pixel of the block used, back to the tile's start.
        hi = wp.tile_extract(wp.tile_max(wp.tile(last_max)), 0) + 1
        warp_hi = hi
        if wp.static(WARP_WALK):
            warp_hi = warp_max(last_max) + 1
        T = PixVec()
        for p in range(PX):
            T[p] = t_final[p]
        buf = PixColor()
        buf_depth = PixVec()
        n_batches = (hi - start + B - 1) // B
        if wp.static(PACKED and COOP):
            ids = wp.tile_empty(shape=(B,), dtype=wp.int32, storage="shared")
            rec = wp.tile_empty(shape=(B, Q), dtype=wp.vec4, storage="shared")
        elif wp.static(PACKED):
            rec = records
        for b in range(n_batches):
            b1 = hi - b * B
            b0 = wp.max(start, b1 - B)
            count = b1 - b0
            if wp.static(PACKED and COOP):
                # The previous batch's walk reads ids (its Gaussians' gradient slots).
                block_barrier()
                gather_records(sorted_ids, records, b0, ids, rec)
                if wp.static(not REC_COLOR):
                    col_t = wp.tile_load_indexed(colors, ids, shape=(B, C), offset=(0, 0), axis=0, storage="shared")
            elif wp.static(COOP):
                ids = wp.tile_load(sorted_ids, shape=(B,), offset=(b0,), storage="shared")
                xy_t = wp.tile_load_indexed(means2d, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                cn_t = wp.tile_load_indexed(conics, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                op_t = wp.tile_load_indexed(opacities, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
                col_t = wp.tile_load_indexed(colors, ids, shape=(B, C), offset=(0, 0), axis=0, storage="shared")
                if wp.static(DEPTH == 1):
                    dep_t = wp.tile_load_indexed(depths, ids, shape=(B,), offset=(0,), axis=0, storage="shared")
            # Entries b0 .. b0 + n_walk - 1 of this batch: none past the warp's last (may be none).
            n_walk = wp.min(count, warp_hi - b0)
            for jj in range(n_walk):
                j = n_walk - 1 - jj
                g = GradVec()
                touched = False
                if wp.static(COOP):
                    gid = ids[j]
                    row = j
                else:
                    gid = sorted_ids[b0 + j]
                    row = gid
                if wp.static(PACKED):
                    # A Gaussian whose blending box the warp's pixels all miss adds nothing to them.
                    # Warp-uniform: the whole warp skips together, before its vote. (The forward tests
                    # the box on the CPU only: on CUDA its work per Gaussian is short, and with the
                    # test it measured slower; docs/results.md, "Blending boxes".)
                    if outside_box(rec, row, band[0], band[1], band[2], band[3]):
                        continue
                if b0 + j <= last_max:
                    # The geometry, read once for the thread's pixels; colours and depth only where a
                    # pixel blends the Gaussian.
                    if wp.static(PACKED):
                        xy, cn, op = record_geometry(rec, row)
                    elif wp.static(COOP):
                        xy = xy_t[j]
                        cn = cn_t[j]
                        op = op_t[j]
                    else:
                        xy = means2d[gid]
                        cn = conics[gid]
                        op = opacities[gid]
                    dx = xy[0] - fx
                    for p in range(PX):
                        if b0 + j <= last[p]:
                            dy = xy[1] - fy[p]
                            sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
                            vis = wp.exp(-sigma)
                            alpha = wp.min(alpha_max, op * vis)
                            if sigma >= 0.0 and alpha >= alpha_min:
                                touched = True
                                ra = 1.0 / (1.0 - alpha)
                                T[p] = T[p] * ra
                                w = alpha * T[p]
                                d_alpha = float(0.0)
                                for c in range(C):
                                    if wp.static(REC_COLOR):
                                        col = record_word(rec, row, R_COLOR + c)
                                    elif wp.static(COOP):
                                        col = float(col_t[j, c])
                                    else:
                                        col = float(colors[gid, c])
                                    g[_COLOR + c] = g[_COLOR + c] + w * v_img[p * C + c]
                                    d_alpha += (col * T[p] - buf[p * C + c] * ra) * v_img[p * C + c]
                                    buf[p * C + c] = buf[p * C + c] + col * w
                                if wp.static(DEPTH == 1):
                                    if wp.static(PACKED):
                                        dep = record_word(rec, row, R_DEPTH)
                                    elif wp.static(COOP):
                                        dep = dep_t[j]
                                    else:
                                        dep = depths[gid]
                                    g[_COLOR + C] = g[_COLOR + C] + w * v_d[p]
                                    d_alpha += (dep * T[p] - buf_depth[p] * ra) * v_d[p]
                                    buf_depth[p] = buf_depth[p] + dep * w
                                d_alpha += t_final[p] * ra * v_a_eff[p]
                                if op * vis <= alpha_max:
                                    d_sigma = -op * vis * d_alpha
                                    g[_XY + 0] = g[_XY + 0] + d_sigma * (cn[0] * dx + cn[1] * dy)
                                    g[_XY + 1] = g[_XY + 1] + d_sigma * (cn[1] * dx + cn[2] * dy)
                                    g[_CONIC + 0] = g[_CONIC + 0] + 0.5 * d_sigma * dx * dx
                                    g[_CONIC + 1] = g[_CONIC + 1] + d_sigma * dx * dy
                                    g[_CONIC + 2] = g[_CONIC + 2] + 0.5 * d_sigma * dy * dy
                                    g[_OPACITY] = g[_OPACITY] + vis * d_alpha
                # Warp-uniform from here: every lane reaches the shuffles.
                if warp_any(touched):
                    scatter(g, v_gaussians, gid)

    tag = (f"c{C}_t{TS}_b{B}_{'coop' if COOP else 'direct'}_{'depth' if with_depth else 'nodepth'}"
           f"_{color_storage}{'_fast' if fast_math else ''}{'_warpwalk' if warp_walk else ''}"
           f"{'_packed' if packed else ''}")
    backward_tag = tag + (f"_r{max_registers}" if max_registers else "") + (f"_px{PX}" if PX > 1 else "")
    forward.__name__ = forward.__qualname__ = f"blend_forward_{tag}"
    backward.__name__ = backward.__qualname__ = f"blend_backward_{backward_tag}"
    # fast_math is a module option: each variant gets its own module.
    options = dict(enable_backward=False, module="unique", module_options={"fast_math": fast_math})
    registers = {"cuda_max_registers": max_registers} if max_registers else {}
    return wp.kernel(forward, **options), wp.kernel(backward, **options, **registers)
