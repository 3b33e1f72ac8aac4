"""The hidden render of a box-frame key, trained on the pixels its box can reach.

In the box frame every hidden Gaussian's centre lies in the key's box, and the object payload's
hidden view shows the object on its background: outside the box's projection both the hidden
render and its target are background (up to the tails of splats near the box's faces). Training
renders and scores only a tile-aligned rectangle around that projection, which can be a fraction of
the view, and weighs the image term by that share, so that each pixel's gradient is what the whole
view's mean would give it.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..data import Camera

# Pixels kept beyond the box's projection, for the tails of splats whose centres lie near its faces:
# a fixed part and a share of the projection's larger side.
MARGIN_PX = 16
MARGIN_SHARE = 0.1
# A crop of more than this share of the view saves too little to give up rendering it whole.
MAX_SHARE = 0.5
# Corners nearer the camera plane than this (camera units) leave the view whole: the projection of
# a box that reaches behind the camera is unbounded.
NEAR = 1e-3


@dataclasses.dataclass(frozen=True)
class Crop:
    """A view restricted to a rectangle: ``camera`` renders rows ``rows`` and columns ``cols`` of
    the view (the intrinsics' principal point moved by the rectangle's corner); ``share`` is the
    rectangle's pixel count over the view's."""

    camera: Camera
    rows: slice
    cols: slice
    share: float


def box_crop(camera: Camera, box: np.ndarray, tile: int) -> Crop | None:
    """The tile-aligned rectangle of ``camera``'s view that holds the projection of ``box`` [2, 3]
    (centre, half-extent; world units) and a margin, or None where the view is better rendered whole
    (the box reaches behind the camera, lies outside the view, or the rectangle exceeds MAX_SHARE)."""
    centre, half = np.asarray(box, dtype=np.float64)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners = centre + signs * half  # [8, 3]
    uv, depth = camera.project(corners)
    if (depth <= NEAR).any():
        return None
    u, v = uv[:, 0], uv[:, 1]
    margin = MARGIN_PX + MARGIN_SHARE * max(u.max() - u.min(), v.max() - v.min())
    # On the view's tile grid, the crop's tiles are the view's own: each holds the same pixels and
    # Gaussians, so the crop does the view's work on those tiles and no more.
    x0 = max(0, math.floor((u.min() - margin) / tile) * tile)
    y0 = max(0, math.floor((v.min() - margin) / tile) * tile)
    x1 = min(camera.width, math.ceil((u.max() + margin) / tile) * tile)
    y1 = min(camera.height, math.ceil((v.max() + margin) / tile) * tile)
    if x1 <= x0 or y1 <= y0:
        return None
    share = (x1 - x0) * (y1 - y0) / (camera.width * camera.height)
    if share > MAX_SHARE:
        return None
    K_crop = camera.K.copy()
    K_crop[0, 2] -= x0
    K_crop[1, 2] -= y0
    cropped = dataclasses.replace(camera, name=f"{camera.name}[{y0}:{y1},{x0}:{x1}]", K=K_crop, width=x1 - x0,
                                  height=y1 - y0, image=None, alpha=None, hidden=None, hidden_alpha=None)
    return Crop(cropped, slice(y0, y1), slice(x0, x1), share)
