"""``Kept``: a value derived from some objects, reused while they are unchanged.

Training derives a few things from the same tensors step after step (the box frame's serving mask
from the anchor positions, each anchor's bit projection): recomputing them costs launches and
host reads. "Unchanged" means the same objects, and no tensor among them written in place since
(torch counts in-place writes in ``Tensor._version``); a replaced tensor is a new object.
"""
from __future__ import annotations

from typing import Callable


class Kept:
    """One kept value and the sources it was derived from."""

    def __init__(self):
        self._sources: tuple = ()
        self._versions: tuple = ()
        self._value = None
        self._filled = False

    def get(self, sources: tuple, derive: Callable[[], object]):
        """The value kept for ``sources`` (tensors or any objects, compared by identity), or
        ``derive()`` when they differ from last time's or a tensor among them was written in place."""
        versions = tuple(getattr(s, "_version", None) for s in sources)
        if not (self._filled and len(sources) == len(self._sources) and versions == self._versions
                and all(a is b for a, b in zip(sources, self._sources))):
            self._value = derive()
            self._sources, self._versions, self._filled = tuple(sources), versions, True
        return self._value
