"""``Lease``: marks a captured graph busy while an autograd graph may still run its backward.

A replayed graph reads and writes fixed buffers, so a second forward of the same graph before the
first one's backward would overwrite what that backward reads. Whoever replays takes a lease at
the forward and releases it when the backward ran; if the autograd graph is freed without a
backward, the lease goes with it (a finalizer), so a graph is never left busy for good.
"""
from __future__ import annotations

import weakref


class Lease:
    """Sets ``entry.busy`` while this object lives and until ``release()``."""

    def __init__(self, entry):
        self.entry = entry
        entry.busy = True
        self._finalizer = weakref.finalize(self, _release, entry)

    def release(self) -> None:
        self._finalizer()


def _release(entry) -> None:
    entry.busy = False
