"""Where a training step's time goes: section timers around the parts of ``ScaffoldTrainer.step``
and ``SecureTrainer.step`` (scripts/profile_step.py prints them side by side).

``profile_steps(trainer, steps)`` wraps, for its duration only, the trainer's public and hidden
renders (and inside them ``rasterize``, so that "heads" is a render's time without it), the image
losses, ``loss.backward`` (and inside it the rasterizer's backward), the gradient check, the
densification strategy, Adam, the post-update hook (SecureGS's bit projection) and ``zero_grad``.
Each section synchronises the device on entry and exit (``torch.cuda.synchronize``), so its time is
the GPU work it queued plus its host time, and nested sections are subtracted from their parent
("other": what ``step`` does outside every section). Those synchronisations slow the step down:
``step_ms`` times the same number of steps without them.

``census_syncs(trainer, steps)`` (CUDA only) finds where a step waits for the device.
"""
from __future__ import annotations

import bisect
import collections
import contextlib
import time
import traceback
import warnings

import torch

from . import render as render_module
from .raster_graph import _CapturedRasterize
from .rasterizer import _Rasterize
from .train import base as train_base

# Section names, in the order of a step.
SECTIONS = ("public heads", "public rasterize", "hidden heads", "hidden rasterize", "hidden branch other",
            "image losses", "backward (autograd, MLPs)", "rasterize backward", "gradient check", "strategy",
            "adam", "after update", "zero_grad", "other")


class SectionTimer:
    """Exclusive wall time per section name, synchronising ``device`` around each section."""

    def __init__(self, device: torch.device):
        self.cuda = torch.device(device).type == "cuda"
        self.totals: dict[str, float] = {}
        self._children: list[float] = []  # per open section: time spent in its nested sections
        self._names: list[str] = []

    def _sync(self):
        # Inside a CUDA graph's capture (a replayed hidden branch capturing again after an overflow,
        # secure.hidden_graph) a synchronisation would break the capture: the section then times
        # host work only.
        if self.cuda and not torch.cuda.is_current_stream_capturing():
            torch.cuda.synchronize()

    @property
    def current(self) -> str | None:
        """Name of the innermost open section."""
        return self._names[-1] if self._names else None

    @contextlib.contextmanager
    def section(self, name: str):
        self._sync()
        t0 = time.perf_counter()
        self._children.append(0.0)
        self._names.append(name)
        try:
            yield
        finally:
            self._sync()
            elapsed = time.perf_counter() - t0
            self._names.pop()
            nested = self._children.pop()
            self.totals[name] = self.totals.get(name, 0.0) + elapsed - nested
            if self._children:
                self._children[-1] += elapsed

    def timed(self, fn, name):
        """``fn`` run inside section ``name`` (a string, or a function of the enclosing section's name)."""
        def wrapper(*args, **kwargs):
            with self.section(name(self.current) if callable(name) else name):
                return fn(*args, **kwargs)
        return wrapper


_MISSING = object()


@contextlib.contextmanager
def _patched(patches):
    """Set each (object, attribute, value) for the duration; afterwards put back what the object's
    own ``__dict__`` held (a staticmethod stays one), or remove the attribute where it held none."""
    saved = [(obj, attr, vars(obj).get(attr, _MISSING)) for obj, attr, _ in patches]
    try:
        for obj, attr, value in patches:
            setattr(obj, attr, value)
        yield
    finally:
        for obj, attr, value in reversed(saved):
            if value is _MISSING:
                delattr(obj, attr)
            else:
                setattr(obj, attr, value)


def _branch(parent: str | None) -> str:
    return "hidden" if parent is not None and parent.startswith("hidden") else "public"


def _section_patches(trainer, wrap) -> list:
    """(object, attribute, wrapped) for every section of a step; ``wrap(fn, name)`` wraps one."""
    patches = [
        (trainer, "step", wrap(trainer.step, "other")),
        (trainer, "render", wrap(trainer.render, "public heads")),
        (trainer, "image_losses", wrap(trainer.image_losses, "image losses")),
        (trainer, "extra_losses", wrap(trainer.extra_losses, "hidden branch other")),
        (trainer, "after_update", wrap(trainer.after_update, "after update")),
        (trainer.optimizer, "step", wrap(trainer.optimizer.step, "adam")),
        (trainer.optimizer, "zero_grad", wrap(trainer.optimizer.zero_grad, "zero_grad")),
        (trainer.strategy, "step_post_backward", wrap(trainer.strategy.step_post_backward, "strategy")),
        (render_module, "rasterize", wrap(render_module.rasterize, lambda p: f"{_branch(p)} rasterize")),
        (train_base, "nonfinite_gradient_counts", wrap(train_base.nonfinite_gradient_counts, "gradient check")),
        (torch.Tensor, "backward", wrap(torch.Tensor.backward, "backward (autograd, MLPs)")),
        (_Rasterize, "backward", staticmethod(wrap(_Rasterize.backward, "rasterize backward"))),
        (_CapturedRasterize, "backward", staticmethod(wrap(_CapturedRasterize.backward, "rasterize backward"))),
    ]
    if hasattr(trainer, "render_hidden"):
        patches.append((trainer, "render_hidden", wrap(trainer.render_hidden, "hidden heads")))
    if hasattr(trainer, "_finishing_optimizer"):  # the finishing phase steps its own Adam (made here if not yet)
        finishing = trainer._finishing_optimizer()
        patches += [(finishing, "step", wrap(finishing.step, "adam")),
                    (finishing, "zero_grad", wrap(finishing.zero_grad, "zero_grad"))]
    return patches


def profile_steps(trainer, steps: int) -> dict:
    """Run ``steps`` training steps of ``trainer`` with section timers, then ``steps`` more without.

    Returns {"sections_ms": {section: mean ms per step}, "profiled_step_ms": mean ms of a step with
    the timers, "step_ms": mean ms of a step without them}.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    timer = SectionTimer(trainer.device)
    with _patched(_section_patches(trainer, timer.timed)):
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.step()
        profiled = (time.perf_counter() - t0) / steps
    timer._sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    timer._sync()
    plain = (time.perf_counter() - t0) / steps
    sections = {name: 1000 * timer.totals.get(name, 0.0) / steps for name in SECTIONS}
    return {"sections_ms": sections, "profiled_step_ms": 1000 * profiled, "step_ms": 1000 * plain}


# What ``count_ops`` counts per section, per step: torch.profiler's top-level aten ops (forward and
# those the autograd backward runs), the autograd nodes evaluated, the host reads of device values
# (item, nonzero, equal: a synchronisation each on CUDA), the CUDA kernel launches and copies (memsets
# included; CUDA only), and the Warp launches.
COUNTS = ("aten ops", "autograd nodes", "host reads", "cuda launches", "cuda copies", "warp launches")
HOST_COUNTS = ("aten ops", "autograd nodes", "host reads", "warp launches")  # those a CPU run has
_CUDA_LAUNCHES = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx",
                  "cudaGraphLaunch")
_HOST_READS = ("aten::item", "aten::_local_scalar_dense", "aten::nonzero", "aten::equal", "aten::is_nonzero")
_SECTION_MARK = "step_profile::"


class SectionCounter(SectionTimer):
    """Marks each section with a profiler range (``record_function``) instead of timing it, and counts
    the Warp launches made inside it; nothing is synchronised."""

    def __init__(self, device: torch.device):
        super().__init__(device)
        self.cuda = False
        self.warp_launches: dict[str, int] = {}

    @contextlib.contextmanager
    def section(self, name: str):
        self._names.append(name)
        try:
            with torch.profiler.record_function(_SECTION_MARK + name):
                yield
        finally:
            self._names.pop()

    def counted(self, fn):
        """``fn`` (a Warp launch function), counted against the current section."""
        def wrapper(*args, **kwargs):
            name = self.current or "other"
            self.warp_launches[name] = self.warp_launches.get(name, 0) + 1
            return fn(*args, **kwargs)
        return wrapper


def _count_kind(event) -> str | None:
    """Which of COUNTS a profiler event adds to (None: none)."""
    name = event.name
    if name in _CUDA_LAUNCHES:
        return "cuda launches"
    if name.startswith(("cudaMemcpy", "cudaMemset")):
        return "cuda copies"
    if name.startswith("autograd::engine::evaluate_function"):
        return "autograd nodes"
    if name in _HOST_READS:  # nested in another host read (item's _local_scalar_dense) it is that one
        return None if any(p.name in _HOST_READS for p in _ancestors(event)) else "host reads"
    if name.startswith("aten::") and not any(p.name.startswith("aten::") for p in _ancestors(event)):
        return "aten ops"
    return None


def _ancestors(event):
    parent = event.cpu_parent
    while parent is not None:
        yield parent
        parent = parent.cpu_parent


def count_ops(trainer, steps: int) -> dict:
    """Run ``steps`` training steps of ``trainer`` under torch.profiler and count, per section and
    in all, what each step launches (COUNTS). A host read is counted apart from the aten ops (a
    top-level ``item`` is one host read and no aten op). Events are given to the innermost section
    whose time range holds their start, so that the autograd backward's work on CUDA, which runs on
    another thread, falls in the backward sections.

    Returns {"per_step": {section: {count: mean per step}}, "total": {count: mean per step}}.
    """
    import warp as wp

    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    counter = SectionCounter(trainer.device)
    patches = _section_patches(trainer, counter.timed)
    patches += [(wp, "launch", counter.counted(wp.launch)), (wp, "capture_launch", counter.counted(wp.capture_launch))]
    activities = [torch.profiler.ProfilerActivity.CPU]
    if trainer.device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with _patched(patches), torch.profiler.profile(activities=activities) as prof:
        for _ in range(steps):
            trainer.step()
    events = list(prof.events())
    marks = sorted(((e.time_range.start, e.time_range.end, e.name[len(_SECTION_MARK):]) for e in events
                    if e.name.startswith(_SECTION_MARK)), key=lambda m: m[0])
    starts = [lo for lo, _, _ in marks]
    counts = {name: dict.fromkeys(COUNTS, 0.0) for name in SECTIONS}
    for event in events:
        kind = _count_kind(event)
        if kind is None:
            continue
        # Sections nest: the innermost holding the event is the latest-starting one that holds it.
        start, section = event.time_range.start, "other"
        for i in range(bisect.bisect_right(starts, start) - 1, -1, -1):
            if start <= marks[i][1]:
                section = marks[i][2]
                break
        counts[section][kind] += 1
    for name, n in counter.warp_launches.items():
        counts[name]["warp launches"] += n
    per_step = {name: {kind: n / steps for kind, n in c.items()} for name, c in counts.items()}
    total = {kind: sum(c[kind] for c in per_step.values()) for kind in COUNTS}
    return {"per_step": per_step, "total": total}


def count_table(results: dict, title: str, kinds=HOST_COUNTS) -> str:
    """Markdown: one row per section, for each trainer in ``results`` ({label: count_ops}) one column
    per count in ``kinds`` (COUNTS on CUDA)."""
    labels = list(results)
    head = [f"{label} {kind}" for label in labels for kind in kinds]
    lines = [title, "", "| section | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for name in (*SECTIONS, None):
        row = [results[k]["total"] if name is None else results[k]["per_step"][name] for k in labels]
        cells = [f"{r[kind]:.0f}" for r in row for kind in kinds]
        if name is None:
            lines.append("| **step** | " + " | ".join(f"**{c}**" for c in cells) + " |")
        else:
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def profile_table(results: dict, title: str) -> str:
    """Markdown: one row per section, one column per trainer in ``results`` ({label: profile_steps})."""
    labels = list(results)
    lines = [title, "", "| section | " + " | ".join(f"{label} ms" for label in labels) + " |",
             "|---|" + "---|" * len(labels)]
    for name in SECTIONS:
        lines.append(f"| {name} | " + " | ".join(f"{results[k]['sections_ms'][name]:.2f}" for k in labels) + " |")
    for key, label in (("profiled_step_ms", "step, with the section timers"), ("step_ms", "step, no timers")):
        lines.append(f"| **{label}** | " + " | ".join(f"**{results[k][key]:.2f}**" for k in labels) + " |")
    return "\n".join(lines)


# CUDA runtime calls that can block the host (a copy blocks when it reads back to host memory).
_BLOCKING = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy",
             "cudaMemcpyAsync")


def census_syncs(trainer, steps: int) -> dict:
    """Where ``steps`` training steps of a CUDA ``trainer`` wait for the device, seen two ways.

    Returns {"lines": {place: per step}, "runtime": {call: per step}}:
    ``lines`` counts torch.cuda.set_sync_debug_mode("warn")'s warnings by the innermost three
    frames inside securegs_warp (the Python lines that synchronise); ``runtime`` counts
    torch.profiler's CUDA runtime calls that can block, each with up to six parent ops, which names
    what the warnings cannot: a C++ autograd node's read (the second run of ``steps`` steps).
    """
    if trainer.device.type != "cuda":
        raise ValueError(f"census_syncs needs a CUDA trainer (synchronisations are CUDA's), got {trainer.device}")
    lines = collections.Counter()

    def note(message, category, filename, lineno, file=None, line=None):
        # This function's own frame left out: the three are the lines that synchronised and their callers.
        frames = [f for f in traceback.extract_stack()[:-1] if "securegs_warp" in f.filename]
        lines[" < ".join(f"{f.filename.split('securegs_warp/')[-1]}:{f.lineno}" for f in frames[-3:][::-1])] += 1

    torch.cuda.synchronize()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = note
        torch.cuda.set_sync_debug_mode("warn")
        try:
            for _ in range(steps):
                trainer.step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    runtime = collections.Counter()
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(steps):
            trainer.step()
    for event in prof.events():
        if event.name in _BLOCKING:
            parents = [p.name for p, _ in zip(_ancestors(event), range(6))]
            runtime[" <- ".join([event.name, *parents])] += 1
    return {"lines": {k: n / steps for k, n in lines.most_common()},
            "runtime": {k: n / steps for k, n in runtime.most_common()}}


def census_table(results: dict, title: str) -> str:
    """Markdown: for each trainer in ``results`` ({label: census_syncs}) its places, most first."""
    out = [title]
    for label, census in results.items():
        for kind, heading in (("lines", "synchronising lines"), ("runtime", "CUDA runtime calls that can block")):
            out += ["", f"{label}: {heading}, {sum(census[kind].values()):.1f} per step", "",
                    "| per step | where |", "|---|---|"]
            out += [f"| {n:.1f} | `{where}` |" for where, n in census[kind].items()]
    return "\n".join(out)
