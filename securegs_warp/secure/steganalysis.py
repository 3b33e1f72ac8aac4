"""Steganalysis of a public release: what an attacker who holds only the file can say about whether
it hides a 3D object, and where.

The anchor cloud is the release's geometry. A hidden object that grew anchors of its own leaves a
region where anchors are denser, closer together and more isolated from the rest of the cloud than
the scene's own surfaces are. Each test compares one region (a cell of a grid over the cloud)
against all the other regions:

- ``density_z``: the cell's anchor count against the occupied cells' counts (robust z-score of the
  log count: median and MAD).
- ``nn_z``: the cell's anchors' nearest-neighbour distances against the rest of the cloud's
  (Mann–Whitney U, as a z-score; positive when the cell is tighter).
- ``isolation``: the fraction of the cell's 26 neighbours that hold no anchor (a cluster in empty
  space: near 1; a patch of a wall or floor that continues: lower).

A cell's score is ``(max(density_z, 0) + max(nn_z, 0)) · (0.5 + isolation)`` (see
:func:`region_scores`); the release's score is the highest cell's, and the suspicious box is that
cell grown over its suspicious neighbours. With a reference (a plain Scaffold-GS model of the same
scene) the density test is the release's count against the reference's in the same cell (a Poisson
z-score), and the per-attribute distributions are compared (sliced Wasserstein distances). With
the key as well, :func:`leakage` measures what the tests try to find: how many anchors lie on the
hidden object's surface, estimated from the hidden Gaussians the key decodes. The tests take numpy
arrays (``release_arrays`` and ``hidden_surface`` make them from a model); nothing here trains.
"""
from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.stats import wasserstein_distance
from sklearn.neighbors import NearestNeighbors

from .container import KeyViews

# Cells per side of the grid over the cloud's central extent (1st to 99th percentile per axis).
GRID_CELLS = 16
# A cell needs this many anchors for its tests (fewer: its statistics are noise).
MIN_CELL_ANCHORS = 8
# Cells scoring at least this fraction of the best one join its suspicious box when they touch it.
BOX_JOIN = 0.5
# Random directions of the sliced Wasserstein distance.
SLICES = 64


def _grid(xyz: np.ndarray, extent: tuple[np.ndarray, np.ndarray] | None = None):
    """(cell index [N, 3] int, lo [3], cell size [3]) of a grid of GRID_CELLS per side over the
    central extent of positions [N, 3] (or over ``extent``); anchors outside fall in the border cells."""
    lo, hi = extent if extent is not None else (np.percentile(xyz, 1, axis=0), np.percentile(xyz, 99, axis=0))
    size = np.maximum((hi - lo) / GRID_CELLS, 1e-9)
    cell = np.clip(np.floor((xyz - lo) / size), 0, GRID_CELLS - 1).astype(np.int64)
    return cell, lo, size


def nearest_distances(xyz: np.ndarray) -> np.ndarray:
    """Each anchor's distance to its nearest other anchor, [N]."""
    if len(xyz) < 2:
        return np.zeros(len(xyz))
    return NearestNeighbors(n_neighbors=2).fit(xyz).kneighbors(xyz)[0][:, 1]


def _robust_z(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    med = np.median(reference)
    mad = 1.4826 * np.median(np.abs(reference - med)) + 1e-9
    return (values - med) / mad


def region_scores(xyz: np.ndarray, reference: np.ndarray | None = None) -> dict:
    """The region tests over anchor positions [N, 3] (``reference``: a plain model's anchors
    [M, 3] of the same scene, on the same grid).

    Returns dict: ``cells`` [C, 3] int (occupied cells with enough anchors), ``counts`` [C],
    ``density_z`` [C], ``nn_z`` [C], ``isolation`` [C], ``score`` [C] and the grid (``lo`` [3],
    ``size`` [3]).
    """
    cell, lo, size = _grid(xyz)
    keys = np.ravel_multi_index(cell.T, (GRID_CELLS,) * 3)
    occupied, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    cells = np.stack(np.unravel_index(occupied, (GRID_CELLS,) * 3), axis=1)
    # Mann–Whitney U of each cell's nearest-neighbour distances against the rest's, from one ranking
    # of all of them: U counts the (rest, cell) pairs where the rest's distance is the larger.
    rank = stats.rankdata(nearest_distances(xyz))
    rank_sum = np.bincount(inverse, weights=rank, minlength=len(occupied))
    if reference is None:
        density_z = _robust_z(np.log(counts), np.log(counts))
    else:
        ref_cell = np.clip(np.floor((reference - lo) / size), 0, GRID_CELLS - 1).astype(np.int64)
        ref_counts = np.bincount(np.ravel_multi_index(ref_cell.T, (GRID_CELLS,) * 3), minlength=GRID_CELLS ** 3)
        expected = ref_counts[occupied] * len(xyz) / max(len(reference), 1)
        density_z = (counts - expected) / np.sqrt(expected + 1.0)
    grid = np.zeros((GRID_CELLS + 2,) * 3, dtype=bool)
    grid[tuple((cells + 1).T)] = True
    around = sum(np.roll(grid, (dx, dy, dz), axis=(0, 1, 2)).astype(np.int64)
                 for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) != (0, 0, 0))
    isolation = 1.0 - around[tuple((cells + 1).T)] / 26.0
    n_in, n_rest = counts.astype(float), len(xyz) - counts.astype(float)
    u_rest = n_in * n_rest - (rank_sum - n_in * (n_in + 1) / 2)
    nn_z = np.where(n_rest > 0, (u_rest - n_in * n_rest / 2) / np.sqrt(n_in * n_rest * (len(xyz) + 1) / 12.0 + 1e-9),
                    0.0)
    enough = counts >= MIN_CELL_ANCHORS
    # Dense and tight only counts as suspicious in proportion to how alone the cell stands: walls
    # and floors are dense too, but continue into their neighbours.
    score = np.where(enough, (np.maximum(density_z, 0) + np.maximum(nn_z, 0)) * (0.5 + isolation), 0.0)
    return {"cells": cells, "counts": counts, "density_z": density_z, "nn_z": nn_z, "isolation": isolation,
            "score": score, "lo": lo, "size": size}


def suspicious_box(regions: dict) -> tuple[list[float], list[float]] | None:
    """The best cell grown by the touching cells that score at least BOX_JOIN of it: (min corner,
    max corner) in world units, or None without a scoring cell."""
    score = regions["score"]
    if len(score) == 0 or score.max() <= 0:
        return None
    best = int(score.argmax())
    strong = regions["cells"][score >= BOX_JOIN * score[best]]
    member = [regions["cells"][best]]
    grown = True
    while grown:  # flood fill over touching strong cells
        grown = False
        for c in strong:
            if not any((c == m).all() for m in member) and any(np.abs(c - m).max() <= 1 for m in member):
                member.append(c)
                grown = True
    member = np.array(member)
    lo = regions["lo"] + member.min(0) * regions["size"]
    hi = regions["lo"] + (member.max(0) + 1) * regions["size"]
    return lo.tolist(), hi.tolist()


def sliced_wasserstein(a: np.ndarray, b: np.ndarray, seed: int = 0) -> float:
    """Sliced Wasserstein-1 distance between samples [N, D] and [M, D], each dimension first divided
    by the pooled standard deviation (so features and offsets compare on one scale)."""
    a, b = np.asarray(a, np.float64).reshape(len(a), -1), np.asarray(b, np.float64).reshape(len(b), -1)
    scale = np.concatenate([a, b]).std(axis=0) + 1e-9
    a, b = a / scale, b / scale
    directions = np.random.default_rng(seed).normal(size=(SLICES, a.shape[1]))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return float(np.mean([wasserstein_distance(a @ d, b @ d) for d in directions]))


def attribute_distances(release: dict, reference: dict) -> dict:
    """Sliced Wasserstein distance per attribute between two releases' anchors, each a dict of
    arrays [N, ...] (``features``, ``offsets``, ``scales``, ``opacities``: see ``release_arrays``);
    None for an attribute whose per-anchor shapes differ (models of another k or feature width)."""
    return {name: sliced_wasserstein(release[name], reference[name])
                  if release[name].shape[1:] == reference[name].shape[1:] else None
            for name in release if name in reference}


def audit(release: dict, reference: dict | None = None) -> dict:
    """The whole audit of one release (``release_arrays`` of it; ``reference``: a plain model's, or
    None). Returns ``score`` (the most suspicious region's; higher is more suspicious; with a
    reference, its density test is against the reference's count in each cell),
    ``suspicious_box`` (``[min xyz, max xyz]`` or None), ``anchors``, the best region's tests
    (``region``) and, with a reference, ``attribute_distances``."""
    xyz = release["xyz"]
    regions = region_scores(xyz, None if reference is None else reference["xyz"])
    out = {"anchors": int(len(xyz)), "score": float(regions["score"].max()) if len(regions["score"]) else 0.0,
           "suspicious_box": suspicious_box(regions)}
    if len(regions["score"]):
        best = int(regions["score"].argmax())
        out["region"] = {name: float(regions[name][best]) for name in ("counts", "density_z", "nn_z", "isolation")}
    if reference is not None:
        out["attribute_distances"] = attribute_distances(
            {k: v for k, v in release.items() if k != "xyz"}, {k: v for k, v in reference.items() if k != "xyz"})
    return out


def release_arrays(model) -> dict:
    """A ``ScaffoldModel``'s public anchors as numpy arrays: ``xyz`` [N, 3], ``features`` [N, d],
    ``offsets`` [N, 3k] (in units of the anchor's scale, as stored), ``scales`` [N, 6] (log), and
    ``opacities`` [N, k]: the public opacity MLP's output for a view from the cloud's centre (the
    release stores no opacity; this is what any viewer decodes)."""
    import torch

    a = model.anchors
    with torch.no_grad():
        centre = a.xyz.mean(dim=0)
        view = torch.nn.functional.normalize(a.xyz - centre, dim=1)
        dist = (a.xyz - centre).norm(dim=1, keepdim=True)
        feat = model.heads.blend_features(a.feat, view, dist)
        opacity, _, _ = model.heads(feat, view, dist, 0 if model.heads.appearance_dim else None)
    return {"xyz": a.xyz.detach().cpu().numpy(), "features": a.feat.detach().cpu().numpy(),
            "offsets": a.offsets.detach().reshape(a.num_anchors, -1).cpu().numpy(),
            "scales": a.scaling.detach().cpu().numpy(), "opacities": opacity.cpu().numpy()}


def detection_auc(container_scores, plain_scores) -> float:
    """The probability that a container scores above a plain model (ties count half): the area
    under the detector's ROC curve. 0.5 is chance; 1, every container flagged."""
    c, p = np.asarray(container_scores, float), np.asarray(plain_scores, float)
    return float(((c[:, None] > p[None, :]).sum() + 0.5 * (c[:, None] == p[None, :]).sum()) / (len(c) * len(p)))


# The opacity above which a decoded hidden Gaussian marks the hidden surface, unless none reaches it.
SURFACE_OPACITY = 0.5


def surface_opacity(opacities: np.ndarray, min_opacity: float = SURFACE_OPACITY) -> float:
    """The opacity above which hidden Gaussians of opacities [M] mark the hidden surface:
    ``min_opacity``, or half the most opaque one's where none reaches it (a thin or dark object
    drawn by many faint Gaussians, which would otherwise leave its leak unmeasured); nan for none."""
    if not len(opacities):
        return float("nan")
    top = float(opacities.max())
    return min_opacity if top > min_opacity else 0.5 * top


def hidden_surface(model, cameras, samples: int = 4096, min_opacity: float = SURFACE_OPACITY,
                   seed: int = 0) -> tuple[np.ndarray, float]:
    """(points [≤ samples, 3] on the hidden object, the opacity that marked them), from a
    ``SecureModel`` opened with its key: the means of the hidden Gaussians more opaque than
    ``surface_opacity`` decoded with each camera's view directions (``SecureModel.hidden_gaussians``),
    pooled and subsampled."""
    means, opacities = [], []
    for cam in cameras:
        g = model.hidden_gaussians(cam)
        means.append(g["means"].cpu().numpy())
        opacities.append(g["opacities"].reshape(-1).cpu().numpy())
    means = np.concatenate(means) if means else np.zeros((0, 3))
    opacities = np.concatenate(opacities) if opacities else np.zeros(0)
    threshold = surface_opacity(opacities, min_opacity)
    pts = means[opacities > threshold]
    if len(pts) > samples:
        pts = pts[np.random.default_rng(seed).choice(len(pts), samples, replace=False)]
    return pts, threshold


class NoHiddenSurface(ValueError):
    """A key that marks no hidden surface in its container; the message says why."""


def key_surface(model, meta: dict) -> tuple[np.ndarray, float]:
    """``hidden_surface`` of a container opened with its key (``container.open_container``'s model and
    metadata) over the key's hidden views: what audit, attack studies and pictures measure the leak
    around. NoHiddenSurface saying why where there is none."""
    if not model.renders_hidden:
        raise NoHiddenSurface("the key hides no object or scene (bits only): no hidden surface to measure")
    points, threshold = hidden_surface(model, KeyViews.from_metadata(meta, "cpu").hidden)
    if not len(points):
        raise NoHiddenSurface("the key decodes no hidden Gaussian to mark the hidden surface")
    return points, threshold


def leakage(xyz: np.ndarray, hidden_points: np.ndarray, reference_xyz: np.ndarray | None,
            radius_fraction: float = 0.03) -> dict:
    """``exposure`` of anchors [N, 3] around the whole hidden surface [M, 3] (the file holds no
    scene points to tell its hidden-only part; where the object overlaps the scene, both models
    have anchors there and the ratio leans toward 1), r = ``radius_fraction`` of its bounding-box
    diagonal. With a reference's anchors [P, 3] (a plain model of the scene), ``density_ratio`` is
    the release's anchors within r of the surface over the reference's (None when it has none)."""
    from .security import exposure

    radius = radius_fraction * float(np.linalg.norm(np.ptp(hidden_points, axis=0)))
    nowhere = hidden_points.max(axis=0, keepdims=True) + 1e6  # no scene point near: every sample counts
    exposed = exposure(xyz, hidden_points, nowhere, radius)
    out = {"coverage": exposed["coverage"], "surface_density": exposed["surface_density"], "radius": radius}
    if reference_xyz is not None:
        base = exposure(reference_xyz, hidden_points, nowhere, radius)
        out["reference_coverage"] = base["coverage"]
        out["density_ratio"] = (exposed["surface_density"] / base["surface_density"]
                                if base["surface_density"] > 0 else None)
    return out


def auc_by_model(runs: list[dict[str, np.ndarray]], plain: str, with_reference: bool = False,
                 covers: list | None = None) -> dict:
    """Detection AUC of the audit's score for each kind of model in ``runs`` (one dict per run of
    one scene: model label -> anchor positions [N, 3]; ``plain`` labels the plain Scaffold-GS
    models). ``with_reference``: every model of run i is audited against the plain model of every
    other run j trained apart (the attacker's reference, never the same training as run i's own
    plain model); otherwise without a reference. ``covers``: per run, what its plain model's training
    depends on (scene, budget, seed: not the hidden object, which a plain model never sees); runs of
    one cover are not each other's references, since their plain models are the same training.
    None: every run's cover is its own. Returns {label: {"auc", "scores"}}, plain's scores under
    ``plain``."""
    if any(plain not in run for run in runs):
        raise ValueError(f"every run needs a plain model labelled {plain!r}")
    covers = list(range(len(runs))) if covers is None else list(covers)
    if len(covers) != len(runs):
        raise ValueError(f"{len(covers)} covers for {len(runs)} runs")
    scores: dict[str, list[float]] = {}
    for i, run in enumerate(runs):
        references = [other[plain] for j, other in enumerate(runs) if covers[j] != covers[i]] \
            if with_reference else [None]
        if not references:
            raise ValueError("auditing against a reference needs runs of at least two covers (scene, budget, seed)")
        for label, xyz in run.items():
            scores.setdefault(label, []).extend(
                float(region_scores(xyz, ref)["score"].max(initial=0.0)) for ref in references)
    return {label: {"scores": s, **({} if label == plain else {"auc": detection_auc(s, scores[plain])})}
            for label, s in scores.items()}
