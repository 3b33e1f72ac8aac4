"""Tile binning: which Gaussians touch which image tile, sorted front to back within each tile.

Pipeline (driven by ``securegs_warp.rasterizer``):
1. ``count_tiles``: tiles covered by each Gaussian's screen rectangle (int64: 3M Gaussians times
   dozens of tiles overflows int32).
2. inclusive prefix sum of the counts (``wp.utils.array_scan``): its last entry is the total, read
   on the host (the render's one synchronisation); each Gaussian writes at ``ends[i] - counts[i]``.
3. ``emit_intersections``: one 64-bit key per (Gaussian, tile): tile id in the high 32 bits, the
   float32 depth's bit pattern zero-extended in the low 32 (depths are > 0, so their bit patterns
   sort like the values; sign extension would corrupt the tile id).
4. ``wp.utils.radix_sort_pairs`` on the keys (stable, so equal depths keep Gaussian order).
5. ``tile_ranges``: [start, end) of each tile's run in the sorted list.
"""
import warp as wp

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


@wp.kernel
def count_tiles(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    counts: wp.array(dtype=wp.int64),
):
    i = wp.tid()
    r = radii[i]
    n = wp.int64(0)
    if r[0] > 0 and r[1] > 0:
        rect = tile_rect(means2d[i], r, tile_size, tiles_x, tiles_y)
        n = wp.int64((rect[2] - rect[0]) * (rect[3] - rect[1]))
    counts[i] = n


@wp.kernel
def emit_intersections(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    depth_bits: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    r = radii[i]
    if r[0] > 0 and r[1] > 0:
        rect = tile_rect(means2d[i], r, tile_size, tiles_x, tiles_y)
        low = wp.int64(depth_bits[i]) & wp.int64(0xFFFFFFFF)
        k = ends[i] - counts[i]
        for ty in range(rect[1], rect[3]):
            for tx in range(rect[0], rect[2]):
                keys[k] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | low
                values[k] = i
                k += wp.int64(1)


@wp.kernel
def tile_ranges(keys: wp.array(dtype=wp.int64), count: int, ranges: wp.array2d(dtype=wp.int32)):
    """ranges[t] = [start, end) in the sorted list; tiles without Gaussians stay [0, 0).

    Start and end of one tile are written by different threads, hence one int per slot.
    """
    i = wp.tid()
    tile = int(keys[i] >> wp.int64(32))
    if i == 0 or int(keys[i - 1] >> wp.int64(32)) != tile:
        ranges[tile, 0] = i
    if i == count - 1 or int(keys[i + 1] >> wp.int64(32)) != tile:
        ranges[tile, 1] = i + 1
