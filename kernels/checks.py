"""Input checks on the device, for renders replayed from graphs (securegs_warp.raster_graph): a
replay cannot stop on the host to look at its inputs, so it writes flags that the host reads later."""
from typing import Any

import warp as wp


@wp.kernel
def flag_nonfinite(values: wp.array(dtype=Any), ends: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int64),
                   first_slot: int):
    """status[first_slot + s] = 1 where a value of segment s of ``values`` is NaN or infinite;
    untouched otherwise (the caller zeroes it). ``values``: float32 vec4s or float16 scalars, one
    a thread; segment s ends (exclusive) at element ends[s]. Every writer stores the same value, so
    no atomics; only a thread that found one looks up its segment."""
    i = wp.tid()
    if not wp.isfinite(values[i]):
        s = int(0)
        while ends[s] <= i:
            s += 1
        status[first_slot + s] = wp.int64(1)
