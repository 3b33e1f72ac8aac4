"""``render_profile.timeline``: busy, lead and gap time of a GPU timeline and who launched the work
after each gap, on hand-made trace events (the trace itself needs a CUDA device)."""
import pytest

from securegs_warp.render_profile import timeline


def event(cat, name, ts, dur, tid=1, correlation=None):
    e = {"ph": "X", "cat": cat, "name": name, "ts": ts, "dur": dur, "tid": tid}
    if correlation is not None:
        e["args"] = {"correlation": correlation}
    return e


def test_busy_lead_gaps_and_launchers():
    events = [
        # Call 1: the GPU starts 10 µs in, two overlapping kernels, then a 20 µs gap that ends with
        # work launched from inside rasterize (a Python frame of this package around the launch).
        event("user_annotation", "call", 0, 100),
        event("python_function", "securegs_warp/raster_graph.py(150): forward", 5, 60),
        event("cuda_runtime", "cudaLaunchKernel", 6, 1, correlation=1),
        event("cuda_driver", "cuGraphLaunch", 50, 1, correlation=2),
        event("kernel", "a", 10, 20, tid=7, correlation=1),
        event("kernel", "b", 25, 15, tid=7, correlation=1),  # overlaps a: busy 10..40
        event("kernel", "c", 60, 30, tid=7, correlation=2),  # idle 40..60, launched at 50
        # Call 2: one memset 5 µs in, and a 2 µs gap (a launch's own latency: not attributed).
        event("user_annotation", "call", 200, 50),
        event("cuda_runtime", "cudaMemsetAsync", 201, 1, correlation=3),
        event("gpu_memset", "Memset (Device)", 205, 10, tid=7, correlation=3),
        event("kernel", "a", 217, 10, tid=7, correlation=4),
    ]
    t = timeline(events)
    assert t["gpu_busy_ms"] == pytest.approx((30 + 30 + 10 + 10) / 2 / 1000)
    assert t["lead_ms"] == pytest.approx((10 + 5) / 2 / 1000)
    assert t["gaps_ms"] == pytest.approx((20 + 2) / 2 / 1000)
    assert t["launches"] == pytest.approx(3 / 2)  # the kernel launch, the graph launch, the memset
    assert t["gaps_by_launcher_ms"] == {"raster_graph.py(150): forward": pytest.approx(20 / 2 / 1000)}
    assert t["kernels_ms"]["a"] == pytest.approx((20 + 10) / 2 / 1000)


def test_a_call_without_gpu_work_counts_nothing():
    t = timeline([event("user_annotation", "call", 0, 10)])
    assert t["gpu_busy_ms"] == t["lead_ms"] == t["gaps_ms"] == 0.0
