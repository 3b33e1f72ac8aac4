"""Where a render's measured time goes on a CUDA device: the host's own time of a call, and from a
torch.profiler trace the GPU's busy time, its idle time and who launched the work after each idle
gap. The library behind scripts/profile_render.py.

``host_ms(once, runs)`` → median host milliseconds of ``once()``, started on an idle GPU and not
waited for; ``trace(once, runs)`` → the chrome-trace events of ``runs`` calls, each in a "call"
annotation; ``timeline(events)`` → per-call busy, lead and gap milliseconds, launches, the gaps by
launcher and the largest GPU operations.
"""
from __future__ import annotations

import collections
import json
import os
import statistics
import tempfile
import time

import torch

GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")
LAUNCHER_CATEGORIES = ("cuda_runtime", "cuda_driver")
# Gaps shorter than this are a launch's own latency, not the host holding the GPU back.
GAP_US = 5.0


def host_ms(once, runs: int) -> float:
    """Median host milliseconds of ``once()``, each call started on an idle GPU and not waited for."""
    times = []
    for _ in range(runs):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        once()
        times.append(1000 * (time.perf_counter() - t0))
    torch.cuda.synchronize()
    return statistics.median(times)


def trace(once, runs: int) -> list:
    """The chrome-trace events of ``runs`` calls of ``once()``, each in a "call" annotation
    started on an idle GPU."""
    from torch.profiler import ProfilerActivity, profile, record_function

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], with_stack=True) as prof:
        for _ in range(runs):
            torch.cuda.synchronize()
            with record_function("call"):
                once()
        torch.cuda.synchronize()
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        prof.export_chrome_trace(path)
        with open(path) as f:
            return [e for e in json.load(f)["traceEvents"] if e.get("ph") == "X"]


def _label(launcher: dict, python: dict) -> str:
    """The innermost frame of this project's or gsplat's code around a launch (else the launch's
    own name): 'file.py(line): function'."""
    best = None
    for e in python.get(launcher["tid"], ()):
        if e["ts"] <= launcher["ts"] <= e["ts"] + e["dur"] and ("securegs_warp" in e["name"] or "gsplat" in e["name"]
                                                                 or "scripts/" in e["name"]):
            if best is None or e["ts"] >= best["ts"]:
                best = e
    if best is None:
        return launcher["name"]
    name = best["name"]
    return name.rsplit("/", 1)[-1]


def timeline(events: list) -> dict:
    """Per-call means (ms) of busy, lead and gap time on the GPU, host launches per call,
    {label: gap ms per call} and {GPU operation: ms per call} (the largest)."""
    calls = sorted((e for e in events if e.get("cat") == "user_annotation" and e["name"] == "call"),
                   key=lambda e: e["ts"])
    gpu = sorted((e for e in events if e.get("cat") in GPU_CATEGORIES), key=lambda e: e["ts"])
    launchers = {e["args"]["correlation"]: e for e in events
                 if e.get("cat") in LAUNCHER_CATEGORIES and "correlation" in e.get("args", {})}
    python = collections.defaultdict(list)
    for e in events:
        if e.get("cat") == "python_function":
            python[e["tid"]].append(e)
    n_launches = sum(1 for e in launchers.values() if "aunch" in e["name"] or "emcpy" in e["name"]
                     or "emset" in e["name"])
    totals = collections.Counter()
    gaps = collections.Counter()
    kernels = collections.Counter()
    for k, call in enumerate(calls):
        stop = calls[k + 1]["ts"] if k + 1 < len(calls) else float("inf")
        ops = [e for e in gpu if call["ts"] <= e["ts"] < stop]
        if not ops:
            continue
        cursor = call["ts"]
        for e in ops:
            kernels[e["name"][:64]] += e["dur"]
        for i, e in enumerate(ops):
            idle = e["ts"] - cursor
            if idle > 0:
                if i == 0:
                    totals["lead"] += idle
                else:
                    totals["gaps"] += idle
                    if idle > GAP_US:
                        launcher = launchers.get(e.get("args", {}).get("correlation"))
                        gaps[_label(launcher, python) if launcher else e["name"][:40]] += idle
                cursor = e["ts"]
            end = e["ts"] + e["dur"]
            if end > cursor:
                totals["busy"] += end - cursor
                cursor = end
    n = max(len(calls), 1)
    return {"gpu_busy_ms": totals["busy"] / 1000 / n, "lead_ms": totals["lead"] / 1000 / n,
            "gaps_ms": totals["gaps"] / 1000 / n, "launches": n_launches / n,
            "gaps_by_launcher_ms": {k: v / 1000 / n for k, v in gaps.most_common(8)},
            "kernels_ms": {k: v / 1000 / n for k, v in kernels.most_common(16)}}
