"""Input checks on the device, for renders replayed from graphs (securegs_warp.raster_graph): a
replay cannot stop on the host to look at its inputs, so it writes flags that the host reads later."""
from typing import Any

import warp as wp


@wp.kernel
def flag_nonfinite(values: wp.array(dtype=Any), status: wp.array(dtype=wp.int64), slot: int):
    """status[slot] = 1 where any of ``values`` (a flat float32 or float16 array) is NaN or infinite;
    untouched otherwise (the caller zeroes it). Every writer stores the same value, so no atomics."""
    i = wp.tid()
    if not wp.isfinite(values[i]):
        status[slot] = wp.int64(1)
