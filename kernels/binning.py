"""Tile binning: which Gaussians touch which image tile, sorted front to back within each tile.

Pipeline (driven by ``securegs_warp.rasterizer``):
1. ``depth_order_keys``, then ``wp.utils.radix_sort_pairs`` on 32-bit keys: the Gaussians in depth
   order (``order``; the float32 depth's bit pattern as the key: depths are > 0, so their bit
   patterns sort like the values; culled Gaussians, depth 0, come first and bin nowhere).
2. ``count_tiles`` (it needs no order, and runs before step 1's sort), a thread a Gaussian in index
   order (its reads coalesced, where depth order would gather each field from a random row): the
   tiles covered by its screen rectangle; with ``exact`` only the tiles of that rectangle that the
   Gaussian's ellipse at the alpha threshold reaches (``reaches_tile``, Speedy-Splat's AccuTile): a
   thin diagonal Gaussian touches a band of tiles, not its whole bounding square. The answers for a
   rectangle of up to MASK_TILES tiles are kept as a bit mask, so step 4 does not test again. The
   rectangle and the mask are the Gaussian's ``span``, one 16-byte row: step 4 runs in depth order,
   so each of its per-Gaussian reads lands on a random row, and the span is one memory sector
   (a rectangle past MASK_TILES tiles still reads the centre, conic and opacity to test again).
   ``depth_ordered_counts`` then gathers the counts into depth order (int64: 3M Gaussians times
   dozens of tiles overflows int32).
3. inclusive prefix sum of the counts in depth order (``wp.utils.array_scan``): its last entry is the
   total, read on the host (the render's one synchronisation); the j-th writes at ``ends[j] - counts[j]``.
4. ``emit_intersections``: one 32-bit key per (Gaussian, tile), the tile id, in depth order.
5. ``wp.utils.radix_sort_pairs`` on the tile ids' bits only. It is stable, so each tile's run keeps
   the depth order (equal depths in Gaussian order, as step 1 is stable too): the same lists as one
   sort of 64-bit (tile, depth) keys, for a sort of N 32-bit keys and one of M keys of a few passes
   instead of one of M 64-bit keys over 32 + tile bits.
6. ``tile_ranges``: [start, end) of each tile's run in the sorted list.

A captured render (``RasterOptions.capture``) cannot read the count on the host: it sorts a fixed
capacity whose unused keys hold a padding tile id (one past the last tile), which sorts last.
"""
import warp as wp

from .records import SIGMA_SLACK

# Binning is not differentiable: skip generating adjoints.
wp.set_module_options({"enable_backward": False})


@wp.func
def tile_rect(mean2d: wp.vec2, radius: wp.vec2i, tile_size: int, tiles_x: int, tiles_y: int) -> wp.vec4i:
    """[x0, y0, x1, y1) range of tiles that the Gaussian's pixel rectangle touches."""
    ts = float(tile_size)
    tx = mean2d[0] / ts
    ty = mean2d[1] / ts
    rx = float(radius[0]) / ts
    ry = float(radius[1]) / ts
    x0 = wp.clamp(int(wp.floor(tx - rx)), 0, tiles_x)
    y0 = wp.clamp(int(wp.floor(ty - ry)), 0, tiles_y)
    x1 = wp.clamp(int(wp.ceil(tx + rx)), 0, tiles_x)
    y1 = wp.clamp(int(wp.ceil(ty + ry)), 0, tiles_y)
    return wp.vec4i(x0, y0, x1, y1)


# Slack of the ellipse test in sigma = -ln(alpha / opacity) units: the blending kernel evaluates sigma
# in float32 at pixel centres, so a tile whose exact minimum lies a rounding error beyond the
# threshold may still receive a pixel with alpha >= alpha_min. SIGMA_SLACK absolute plus 1e-4 of the
# quadratic form's terms is far above float32 rounding and keeps only a sliver of extra tiles.
_SIGMA_SLACK_REL = 1.0e-4


@wp.func
def edge_sigma(conic: wp.vec3d, inv_diag: wp.vec2d, fixed: wp.float64, lo: wp.float64, hi: wp.float64,
               fixed_is_x: bool) -> wp.vec2d:
    """(min sigma, its terms' magnitude) along one edge of a rectangle in offsets from the centre:
    sigma(dx, dy) = ½(a·dx² + c·dy²) + b·dx·dy with ``fixed`` the edge's dx (``fixed_is_x``) or dy;
    inv_diag = (1/a, 1/c)."""
    a = conic[0]
    b = conic[1]
    c = conic[2]
    # sigma along the edge is ½·q·t² + b·fixed·t + ½·p·fixed², minimal at t = −b·fixed/q, clamped.
    q = c
    p = a
    inv_q = inv_diag[1]
    if not fixed_is_x:
        q = a
        p = c
        inv_q = inv_diag[0]
    t = wp.clamp(-b * fixed * inv_q, lo, hi)
    half = wp.float64(0.5)
    value = half * (q * t * t + p * fixed * fixed) + b * fixed * t
    scale = half * (q * t * t + p * fixed * fixed) + wp.abs(b * fixed * t)
    return wp.vec2d(value, scale)


@wp.struct
class Ellipse:
    """What ``reaches_tile`` needs of one Gaussian, computed once for all its tiles: its centre, its
    conic in float64 (the 1D minimum cancels in float32 for very anisotropic conics), the inverses of
    the conic's diagonal and the sigma at which opacity·e^(−sigma) falls to alpha_min."""

    mean2d: wp.vec2
    conic: wp.vec3d
    inv_diag: wp.vec2d
    limit: wp.float64


@wp.func
def ellipse(mean2d: wp.vec2, conic: wp.vec3, opacity: float, alpha_min: float) -> Ellipse:
    """The ``Ellipse`` of a Gaussian whose opacity reaches alpha_min (callers skip the others)."""
    e = Ellipse()
    e.mean2d = mean2d
    e.conic = wp.vec3d(wp.float64(conic[0]), wp.float64(conic[1]), wp.float64(conic[2]))
    one = wp.float64(1.0)
    e.inv_diag = wp.vec2d(one / e.conic[0], one / e.conic[2])
    e.limit = wp.float64(wp.log(opacity / alpha_min))
    return e


@wp.func
def reaches_tile(e: Ellipse, tx: int, ty: int, tile_size: int) -> bool:
    """Whether some point of tile (tx, ty)'s pixel-centre rectangle has opacity·e^(−sigma) >= alpha_min
    (up to ``SIGMA_SLACK`` and ``_SIGMA_SLACK_REL``): the exact minimum of the convex sigma over the
    rectangle, which is 0 when the centre is inside and otherwise lies on one of its four edges."""
    ts = float(tile_size)
    # Offsets (pixel centre − mean) of the tile's first and last pixel centres.
    x0 = wp.float64(float(tx) * ts + 0.5 - e.mean2d[0])
    x1 = wp.float64(float(tx) * ts + ts - 0.5 - e.mean2d[0])
    y0 = wp.float64(float(ty) * ts + 0.5 - e.mean2d[1])
    y1 = wp.float64(float(ty) * ts + ts - 0.5 - e.mean2d[1])
    zero = wp.float64(0.0)
    if x0 <= zero and zero <= x1 and y0 <= zero and zero <= y1:
        return True
    best = edge_sigma(e.conic, e.inv_diag, x0, y0, y1, True)
    other = edge_sigma(e.conic, e.inv_diag, x1, y0, y1, True)
    if other[0] < best[0]:
        best = other
    other = edge_sigma(e.conic, e.inv_diag, y0, x0, x1, False)
    if other[0] < best[0]:
        best = other
    other = edge_sigma(e.conic, e.inv_diag, y1, x0, x1, False)
    if other[0] < best[0]:
        best = other
    slack = wp.float64(SIGMA_SLACK) + wp.float64(_SIGMA_SLACK_REL) * best[1]
    return best[0] <= e.limit + slack


# Rectangles of at most this many tiles keep the ellipse test's answers as a bit mask from
# ``count_tiles`` to ``emit_intersections``, which then only reads it; larger ones test again.
# 63: the bits of an int64 below its sign bit (torch allocates it; torch 2.1 has no uint64).
MASK_TILES = 63


@wp.func
def masked(rect: wp.vec4i) -> bool:
    """Whether a tile rectangle [x0, y0, x1, y1) is small enough for its ellipse tests to be kept as
    a bit mask (the one rule both binning passes follow)."""
    return (rect[2] - rect[0]) * (rect[3] - rect[1]) <= MASK_TILES


# A span's rectangle holds each tile coordinate in 16 bits.
MAX_TILES_PER_AXIS = 0xFFFF


@wp.func
def pack_rect(rect: wp.vec4i) -> wp.int64:
    """A tile rectangle [x0, y0, x1, y1) (each coordinate at most MAX_TILES_PER_AXIS) as one int64."""
    return (wp.int64(rect[0]) | (wp.int64(rect[1]) << wp.int64(16)) | (wp.int64(rect[2]) << wp.int64(32))
            | (wp.int64(rect[3]) << wp.int64(48)))


@wp.func
def unpack_rect(word: wp.int64) -> wp.vec4i:
    """The rectangle ``pack_rect`` packed."""
    m = wp.int64(MAX_TILES_PER_AXIS)
    return wp.vec4i(int(word & m), int((word >> wp.int64(16)) & m), int((word >> wp.int64(32)) & m),
                    int((word >> wp.int64(48)) & m))


@wp.kernel
def depth_order_keys(depth_bits: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int32),
                     order: wp.array(dtype=wp.int32)):
    """keys[i] = Gaussian i's depth bits, order[i] = i: the inputs of the depth sort."""
    i = wp.tid()
    keys[i] = depth_bits[i]
    order[i] = i


@wp.kernel
def count_tiles(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    alpha_min: float,
    exact: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    tile_counts: wp.array(dtype=wp.int32),
    spans: wp.array2d(dtype=wp.int64),
):
    """tile_counts[i]: the tiles Gaussian i is binned to; where it has a radius, its span [N, 2]:
    spans[i, 0] its tile rectangle (``pack_rect``), spans[i, 1] with ``exact`` which tiles of the
    rectangle its ellipse reaches (bit (ty − y0)·width + (tx − x0)) where ``masked`` keeps them, else 0."""
    i = wp.tid()
    r = radii[i]
    n = int(0)
    if r[0] > 0 and r[1] > 0:
        rect = tile_rect(means2d[i], r, tile_size, tiles_x, tiles_y)
        spans[i, 0] = pack_rect(rect)
        if exact != 0:
            op = opacities[i]
            keep = masked(rect)
            mask = wp.int64(0)
            if op >= alpha_min:
                e = ellipse(means2d[i], conics[i], op, alpha_min)
                b = int(0)
                for ty in range(rect[1], rect[3]):
                    for tx in range(rect[0], rect[2]):
                        if reaches_tile(e, tx, ty, tile_size):
                            n += 1
                            if keep:
                                mask = mask | (wp.int64(1) << wp.int64(b))
                        b += 1
            spans[i, 1] = mask
        else:
            n = (rect[2] - rect[0]) * (rect[3] - rect[1])
    tile_counts[i] = n


@wp.kernel
def depth_ordered_counts(order: wp.array(dtype=wp.int32), tile_counts: wp.array(dtype=wp.int32),
                         counts: wp.array(dtype=wp.int64)):
    """counts[j] = tile_counts[order[j]]: the counts in depth order, for the prefix sum."""
    j = wp.tid()
    counts[j] = wp.int64(tile_counts[order[j]])


@wp.kernel
def emit_intersections(
    order: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    alpha_min: float,
    exact: int,
    counts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    spans: wp.array2d(dtype=wp.int64),
    tile_size: int,
    tiles_x: int,
    capacity: wp.int64,
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """Gaussian i = order[j]'s (tile id, i) pairs at ``ends[j] - counts[j]`` on, from its span (see
    ``count_tiles``; a Gaussian with a count has a radius, hence a span)."""
    j = wp.tid()
    i = order[j]
    if counts[j] > wp.int64(0):
        rect = unpack_rect(spans[i, 0])
        k = ends[j] - counts[j]
        from_mask = exact != 0 and masked(rect)
        mask = wp.int64(0)
        e = Ellipse()
        if from_mask:
            mask = spans[i, 1]
        elif exact != 0:
            e = ellipse(means2d[i], conics[i], opacities[i], alpha_min)
        b = int(0)
        for ty in range(rect[1], rect[3]):
            for tx in range(rect[0], rect[2]):
                hit = exact == 0
                if from_mask:
                    hit = ((mask >> wp.int64(b)) & wp.int64(1)) != wp.int64(0)
                elif exact != 0:
                    hit = reaches_tile(e, tx, ty, tile_size)
                b += 1
                if hit:
                    # A render with a fixed capacity drops what does not fit (and reports it).
                    if k < capacity:
                        keys[k] = ty * tiles_x + tx
                        values[k] = i
                    k += wp.int64(1)


@wp.kernel
def pad_keys(ends: wp.array(dtype=wp.int64), pad: int, keys: wp.array(dtype=wp.int32)):
    """keys[k] = pad for every k past the last intersection (``ends[-1]``, on the device): the
    padding of a fixed-capacity list, a tile id past the last tile, which sorts last. Only the tail
    is written: emit_intersections writes the rest."""
    k = wp.tid()
    if wp.int64(k) >= ends[ends.shape[0] - 1]:
        keys[k] = pad


@wp.kernel
def tile_ranges(keys: wp.array(dtype=wp.int32), count: int, ranges: wp.array2d(dtype=wp.int32)):
    """ranges[t] = [start, end) in the sorted list; tiles without Gaussians stay [0, 0).

    Start and end of one tile are written by different threads, hence one int per slot. Keys with a
    tile id past the last tile are the padding of a fixed-capacity list (they sort last) and skipped.
    """
    i = wp.tid()
    tile = keys[i]
    if tile >= ranges.shape[0]:
        return
    if i == 0 or keys[i - 1] != tile:
        ranges[tile, 0] = i
    if i == count - 1 or keys[i + 1] != tile:
        ranges[tile, 1] = i + 1
