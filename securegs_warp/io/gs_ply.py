"""Standard 3DGS PLY files (what Gaussian splat viewers open), and the vertex-PLY helpers that the
Scaffold-GS files share with them.

A 3DGS PLY holds one ``vertex`` per Gaussian with the float32 properties, in this order,
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``:
opacity as a logit, scales as logs, the rotation as a unit quaternion w first, and the colour as
the degree-0 spherical-harmonic coefficient ``f_dc = (colour - 0.5) / C0`` with ``C0 = 0.28209479``
(viewers compute ``colour = 0.5 + C0 * f_dc``). Normals are written as zeros, as 3DGS does.
A trained 3DGS model adds its higher spherical-harmonic coefficients as ``f_rest_*`` between
``f_dc_*`` and ``opacity`` (:func:`write_gaussians_ply`), and a feature field (GS-Hider) has C
``f_dc_*`` columns instead of 3.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import plyfile
import torch

from .atomic import atomic_write

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical harmonic, 1 / (2 sqrt(pi))."""

GS_PLY_PROPERTIES = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3"]
"""The properties of a degree-0 RGB file (``gaussians_ply_properties(3, 0)``)."""

# Opacities are clamped to [eps, 1 - eps] before the logit: a Gaussian of opacity exactly 0 or 1
# would otherwise be written as -inf / +inf, which viewers do not survive. float32 represents
# 1 - 1e-6 exactly enough (its logit is about 13.8).
_OPACITY_EPS = 1e-6
# Scales are clamped away from 0 before the log for the same reason (log(0) = -inf).
_MIN_SCALE = 1e-12


class PlyFormatError(ValueError):
    """A PLY file is unreadable or lacks what its layout needs. Names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def write_vertex_ply(path: str | os.PathLike, names: Sequence[str], values: np.ndarray) -> None:
    """Write one binary little-endian ``vertex`` element with float32 properties, atomically.

    Args:
        path: the file to write.
        names: the property names, in file order, length P.
        values: [N, P] array; column j is written as property ``names[j]``.
    """
    values = np.ascontiguousarray(values, dtype="<f4")
    if values.ndim != 2 or values.shape[1] != len(names):
        raise ValueError(f"values must be [N, {len(names)}], got {list(values.shape)}")
    # A C-contiguous [N, P] float32 array is bytewise the same as N records of P float32 fields.
    records = values.view(np.dtype([(name, "<f4") for name in names])).reshape(values.shape[0])
    ply = plyfile.PlyData([plyfile.PlyElement.describe(records, "vertex")], byte_order="<")
    atomic_write(path, ply.write)


def read_vertex_ply(path: str | os.PathLike) -> plyfile.PlyElement:
    """Read the ``vertex`` element of a PLY file, raising :class:`PlyFormatError` if there is none."""
    try:
        ply = plyfile.PlyData.read(os.fspath(path))
    except (plyfile.PlyParseError, ValueError) as e:
        # plyfile decodes the header as ASCII: a binary file that is no PLY fails with UnicodeDecodeError
        # (a ValueError); a header naming one property twice or a negative count, with a bare ValueError.
        raise PlyFormatError(path, f"not a readable PLY file ({e})") from e
    if "vertex" not in ply:
        raise PlyFormatError(path, "has no 'vertex' element")
    return ply["vertex"]


def vertex_columns(path: str | os.PathLike, vertex: plyfile.PlyElement, names: Sequence[str]) -> np.ndarray:
    """Stack the named vertex properties into a float32 [N, len(names)] array.

    Raises :class:`PlyFormatError` naming the first property that the file lacks or holds as a list.
    """
    present = {p.name: p for p in vertex.properties}
    for name in names:
        if name not in present:
            raise PlyFormatError(path, f"vertex property '{name}' is missing")
        if isinstance(present[name], plyfile.PlyListProperty):
            raise PlyFormatError(path, f"vertex property '{name}' is a list; expected one number per vertex")
    # A float64 value beyond float32's range becomes inf, which callers that need finite values check.
    with np.errstate(over="ignore"):
        columns = [np.asarray(vertex[name], dtype=np.float32) for name in names]
    return np.stack(columns, axis=1) if columns else np.zeros((vertex.count, 0), np.float32)


def export_3dgs_ply(
    path: str | os.PathLike,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
) -> None:
    """Write Gaussians as a standard 3DGS PLY (SH degree 0), atomically.

    Args:
        means: [M, 3] centres.
        quats: [M, 4] rotations, w first; normalised here.
        scales: [M, 3] linear scales (written as their logs).
        opacities: [M] opacities in [0, 1] (written as logits, clamped to [1e-6, 1 - 1e-6]).
        colors: [M, 3] RGB in [0, 1] (written as f_dc = (colour - 0.5) / C0).
    """
    m = means.shape[0]
    expected = {"means": (means, (m, 3)), "quats": (quats, (m, 4)), "scales": (scales, (m, 3)),
                "opacities": (opacities, (m,)), "colors": (colors, (m, 3))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(tensor.shape)}")
    with torch.no_grad():
        opacity = opacities.detach().to("cpu", torch.float64).clamp(_OPACITY_EPS, 1.0 - _OPACITY_EPS)
        write_gaussians_ply(path, means, quats, torch.log(scales.detach().double().clamp_min(_MIN_SCALE)),
                            torch.log(opacity / (1.0 - opacity)), (colors.detach().double() - 0.5) / SH_C0)


def gaussians_ply_properties(channels: int = 3, rest: int = 0) -> list[str]:
    """The vertex properties of a Gaussians PLY with ``channels`` f_dc columns and ``rest``
    higher-order coefficients per channel (3DGS at degree 3: channels 3, rest 15)."""
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(channels)]
            + [f"f_rest_{i}" for i in range(channels * rest)] + ["opacity"]
            + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def write_gaussians_ply(
    path: str | os.PathLike,
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    features_dc: torch.Tensor,
    features_rest: torch.Tensor | None = None,
) -> None:
    """Write Gaussians in their stored parametrisation as a 3DGS PLY, atomically.

    Args:
        means: [M, 3]. quats: [M, 4] w first (normalised here). log_scales: [M, 3].
        opacity_logits: [M]. features_dc: [M, C] (3DGS: the degree-0 SH coefficient of RGB).
        features_rest: [M, R, C] higher-order coefficients (None or R = 0: none), written
            channel-major (``f_rest_{c·R + r}``) as 3DGS writes its transposed ``features_rest``.
    """
    m = means.shape[0]
    if features_dc.ndim != 2 or features_dc.shape[1] < 1:
        raise ValueError(f"features_dc must be [M, C] with C >= 1, got {list(features_dc.shape)}")
    c = features_dc.shape[1]
    rest = features_dc.new_zeros(m, 0, c) if features_rest is None else features_rest
    n_rest = rest.shape[1] if rest.ndim == 3 else -1
    expected = {"means": (means, (m, 3)), "quats": (quats, (m, 4)), "log_scales": (log_scales, (m, 3)),
                "opacity_logits": (opacity_logits, (m,)), "features_dc": (features_dc, (m, c)),
                "features_rest": (rest, (m, n_rest, c))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(tensor.shape)}")
    with torch.no_grad():
        parts = [t.detach().to("cpu", torch.float64) for t in (means, quats, log_scales, opacity_logits, features_dc, rest)]
        means, quats, log_scales, logits, dc, rest = parts
        values = torch.cat([means, torch.zeros_like(means), dc, rest.transpose(1, 2).reshape(m, -1), logits[:, None],
                            log_scales, torch.nn.functional.normalize(quats, dim=1)], dim=1)
    write_vertex_ply(path, gaussians_ply_properties(c, rest.shape[1]), values.numpy())


def read_gaussians_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Read a Gaussians PLY in its stored parametrisation (inverse of :func:`write_gaussians_ply`).

    The number of channels C and of higher-order coefficients R come from the ``f_dc_*`` and
    ``f_rest_*`` columns present (``f_rest`` must be a multiple of C).

    Returns:
        dict of float32 tensors on ``device``: ``means`` [M, 3], ``quats`` [M, 4] (as stored),
        ``log_scales`` [M, 3], ``opacity_logits`` [M], ``features_dc`` [M, C], ``features_rest``
        [M, R, C].
    """
    vertex = read_vertex_ply(path)
    present = {p.name for p in vertex.properties}
    c = sum(1 for i in range(len(present)) if f"f_dc_{i}" in present)
    n_rest = sum(1 for i in range(len(present)) if f"f_rest_{i}" in present)
    if c == 0:
        raise PlyFormatError(path, "vertex property 'f_dc_0' is missing")
    if n_rest % c:
        raise PlyFormatError(path, f"{n_rest} f_rest_* properties are not a multiple of the {c} colour channels")
    names = [n for n in gaussians_ply_properties(c, n_rest // c) if n not in ("nx", "ny", "nz")]
    values = torch.from_numpy(vertex_columns(path, vertex, names)).to(device)
    means, dc, rest, logits, log_scales, quats = values.split([3, c, n_rest, 1, 3, 4], dim=1)
    return {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": logits[:, 0],
            "features_dc": dc, "features_rest": rest.reshape(rest.shape[0], c, n_rest // c).transpose(1, 2).contiguous()}


def read_3dgs_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Read a standard 3DGS PLY back into rasterizer conventions (inverse of :func:`export_3dgs_ply`).

    Higher-order SH coefficients (``f_rest_*``), if present, are ignored: the colour returned is the
    view-independent degree-0 colour.

    Returns:
        dict of float32 tensors on ``device``: ``means`` [M, 3], ``quats`` [M, 4] (w first, as
        stored), ``scales`` [M, 3] (linear), ``opacities`` [M] (sigmoid of the stored logit),
        ``colors`` [M, 3] (``0.5 + C0 * f_dc``, not clamped).
    """
    stored = read_gaussians_ply(path, device)
    if stored["features_dc"].shape[1] != 3:
        raise PlyFormatError(path, f"holds {stored['features_dc'].shape[1]} colour channels (f_dc_*), not RGB's 3")
    return {
        "means": stored["means"],
        "quats": stored["quats"],
        "scales": torch.exp(stored["log_scales"]),
        "opacities": torch.sigmoid(stored["opacity_logits"]),
        "colors": 0.5 + SH_C0 * stored["features_dc"],
    }
