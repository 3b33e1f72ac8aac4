"""How much of the hidden object's shape the public anchor cloud shows (geometric security).

An attacker who opens the public PLY sees anchors. Where the hidden object overlaps the scene's own
geometry, anchors are expected; on the part of its surface that lies in empty space
("hidden-only" surface: farther than r from every scene point), anchors trace its shape. Measured
inside the hidden object's bounding box (grown by r):

- ``surface_fraction``: the fraction of the box's anchors within r of the hidden-only surface. An
  anchor cloud that outlines the object has a high fraction; anchors spread through the box (RDO
  growing public anchors there) or absent (a plain model) give a low one.
- ``surface_density``: anchors within r of the hidden-only surface per surface sample.
- ``coverage``: the fraction of hidden-only surface samples that have an anchor within r.
"""
from __future__ import annotations

import numpy as np
from sklearn.neighbors import NearestNeighbors

from ..io.atomic import save_figure


def hidden_only_surface(hidden_points: np.ndarray, scene_points: np.ndarray, radius: float) -> np.ndarray:
    """Hidden surface samples [M', 3] farther than ``radius`` from every scene point."""
    dist, _ = NearestNeighbors(n_neighbors=1).fit(scene_points).kneighbors(hidden_points)
    return hidden_points[dist[:, 0] > radius]


def exposure(anchors: np.ndarray, hidden_points: np.ndarray, scene_points: np.ndarray, radius: float) -> dict:
    """The measures above for anchor positions [N, 3] against the hidden object's surface samples
    [M, 3] and the scene's points [P, 3]."""
    bad = int((~np.isfinite(anchors)).any(axis=1).sum())
    if bad:
        raise ValueError(f"{bad} of {len(anchors)} anchors have non-finite positions: the model is corrupt")
    surface = hidden_only_surface(hidden_points, scene_points, radius)
    lo, hi = hidden_points.min(0) - radius, hidden_points.max(0) + radius
    in_box = anchors[((anchors >= lo) & (anchors <= hi)).all(axis=1)]
    out = {"radius": radius, "surface_samples": int(len(surface)), "anchors_in_box": int(len(in_box))}
    if len(surface) == 0:
        return {**out, "surface_fraction": 0.0, "surface_density": 0.0, "coverage": 0.0}
    tree = NearestNeighbors(n_neighbors=1).fit(surface)
    near = tree.kneighbors(in_box)[0][:, 0] <= radius if len(in_box) else np.zeros(0, bool)
    covered = NearestNeighbors(n_neighbors=1).fit(anchors).kneighbors(surface)[0][:, 0] <= radius
    return {**out, "surface_fraction": float(near.mean()) if len(near) else 0.0,
            "surface_density": float(near.sum() / len(surface)), "coverage": float(covered.mean())}


def plot_anchor_clouds(path, clouds: dict[str, np.ndarray], hidden_points: np.ndarray, margin: float = 1.0) -> None:
    """PNG: the anchors of each model around the hidden object, seen from above and from the side,
    with the hidden object's surface samples in a separate first column for reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = hidden_points.min(0) - margin, hidden_points.max(0) + margin
    columns = {"hidden object (reference)": hidden_points, **clouds}
    fig, axes = plt.subplots(2, len(columns), figsize=(4 * len(columns), 8), squeeze=False)
    for col, (name, pts) in enumerate(columns.items()):
        crop = pts[((pts >= lo) & (pts <= hi)).all(axis=1)]
        for row, (a, b, label) in enumerate(((0, 1, "top (x, y)"), (0, 2, "side (x, z)"))):
            ax = axes[row, col]
            ax.scatter(crop[:, a], crop[:, b], s=1.5, c="tab:red" if col == 0 else "black", alpha=0.6, linewidths=0)
            ax.set_xlim(lo[a], hi[a])
            ax.set_ylim(lo[b], hi[b])
            ax.set_aspect("equal")
            ax.set_title(f"{name}\n{label}, {len(crop)} points" if row == 0 else label, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
