"""Standard 3DGS PLY files (what Gaussian splat viewers open), and the vertex-PLY helpers that the
Scaffold-GS files share with them.

A 3DGS PLY holds one ``vertex`` per Gaussian with the float32 properties, in this order,
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``:
opacity as a logit, scales as logs, the rotation as a unit quaternion w first, and the colour as
the degree-0 spherical-harmonic coefficient ``f_dc = (colour - 0.5) / C0`` with ``C0 = 0.28209479``
(viewers compute ``colour = 0.5 + C0 * f_dc``). Normals are written as zeros, as 3DGS does.
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

GS_PLY_PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)

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
    except (plyfile.PlyParseError, UnicodeDecodeError) as e:
        # plyfile decodes the header as ASCII: a binary file that is no PLY fails with UnicodeDecodeError.
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
        means, quats, scales, opacities, colors = (
            t.detach().to("cpu", torch.float64) for t in (means, quats, scales, opacities, colors)
        )
        opacity = opacities.clamp(_OPACITY_EPS, 1.0 - _OPACITY_EPS)
        values = torch.cat(
            [
                means,
                torch.zeros_like(means),
                (colors - 0.5) / SH_C0,
                torch.log(opacity / (1.0 - opacity))[:, None],
                torch.log(scales.clamp_min(_MIN_SCALE)),
                torch.nn.functional.normalize(quats, dim=1),
            ],
            dim=1,
        )
    write_vertex_ply(path, GS_PLY_PROPERTIES, values.numpy())


def read_3dgs_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Read a standard 3DGS PLY back into rasterizer conventions (inverse of :func:`export_3dgs_ply`).

    Higher-order SH coefficients (``f_rest_*``), if present, are ignored: the colour returned is the
    view-independent degree-0 colour.

    Returns:
        dict of float32 tensors on ``device``: ``means`` [M, 3], ``quats`` [M, 4] (w first, as
        stored), ``scales`` [M, 3] (linear), ``opacities`` [M] (sigmoid of the stored logit),
        ``colors`` [M, 3] (``0.5 + C0 * f_dc``, not clamped).
    """
    vertex = read_vertex_ply(path)
    names = [n for n in GS_PLY_PROPERTIES if n not in ("nx", "ny", "nz")]
    values = torch.from_numpy(vertex_columns(path, vertex, names)).to(device)
    means, f_dc, opacity_logit, log_scales, quats = values.split([3, 3, 1, 3, 4], dim=1)
    return {
        "means": means,
        "quats": quats,
        "scales": torch.exp(log_scales),
        "opacities": torch.sigmoid(opacity_logit[:, 0]),
        "colors": 0.5 + SH_C0 * f_dc,
    }
