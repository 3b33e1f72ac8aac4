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
"""
from __future__ import annotations

import contextlib
import time

import torch

from . import render as render_module
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
        if self.cuda:
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


def profile_steps(trainer, steps: int) -> dict:
    """Run ``steps`` training steps of ``trainer`` with section timers, then ``steps`` more without.

    Returns {"sections_ms": {section: mean ms per step}, "profiled_step_ms": mean ms of a step with
    the timers, "step_ms": mean ms of a step without them}.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    timer = SectionTimer(trainer.device)
    patches = [
        (trainer, "step", timer.timed(trainer.step, "other")),
        (trainer, "render", timer.timed(trainer.render, "public heads")),
        (trainer, "image_loss", timer.timed(trainer.image_loss, "image losses")),
        (trainer, "extra_losses", timer.timed(trainer.extra_losses, "hidden branch other")),
        (trainer, "after_update", timer.timed(trainer.after_update, "after update")),
        (trainer.optimizer, "step", timer.timed(trainer.optimizer.step, "adam")),
        (trainer.optimizer, "zero_grad", timer.timed(trainer.optimizer.zero_grad, "zero_grad")),
        (trainer.strategy, "step_post_backward", timer.timed(trainer.strategy.step_post_backward, "strategy")),
        (render_module, "rasterize", timer.timed(render_module.rasterize, lambda p: f"{_branch(p)} rasterize")),
        (train_base, "nonfinite_gradient_counts",
         timer.timed(train_base.nonfinite_gradient_counts, "gradient check")),
        (torch.Tensor, "backward", timer.timed(torch.Tensor.backward, "backward (autograd, MLPs)")),
        (_Rasterize, "backward", staticmethod(timer.timed(_Rasterize.backward, "rasterize backward"))),
    ]
    if hasattr(trainer, "render_hidden"):
        patches.append((trainer, "render_hidden", timer.timed(trainer.render_hidden, "hidden heads")))
    with _patched(patches):
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
