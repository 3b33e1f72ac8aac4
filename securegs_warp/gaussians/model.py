"""``GaussianModel``: explicit 3D Gaussians (plain 3DGS), how they render and how they are stored.

Each Gaussian holds its mean, log scales, a w-first quaternion, an opacity logit and a colour of C
channels: with spherical harmonics (3DGS, C = 3) a degree-0 coefficient ``features_dc`` [N, C] and
``(d + 1)² − 1`` higher ones ``features_rest`` [N, R, C]; without (``sh_degree=None``, a feature
field such as GS-Hider's 16 channels) ``features_dc`` is the rendered value itself and R = 0.
Densification replaces the parameter tensors (row counts change) together with Adam's moments.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from ..io.gs_ply import SH_C0, read_gaussians_ply, write_gaussians_ply
from ..model.anchors import INITIAL_OPACITY, inverse_sigmoid, mean_sq_knn_distance, replace_parameter
from ..model.neural_gaussians import camera_center_from_viewmat
from ..rasterizer import RasterOptions, rasterize
from ..render import camera_tensors

GAUSSIAN_PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "features_dc", "features_rest")
"""Attribute names of the per-Gaussian parameters (each has one row per Gaussian)."""

PLY_FILE = "point_cloud.ply"
"""The file a saved model folder holds (3DGS's name for it)."""

# Real spherical harmonics up to degree 3, in 3DGS's order and signs (its sh_utils.eval_sh).
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
          1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The (degree + 1)² real SH basis functions at unit directions ``dirs`` [N, 3] -> [N, (d+1)²]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * xz, _SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * xy * z, _SH_C3[2] * y * (4 * zz - xx - yy),
                _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
                _SH_C3[5] * z * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def sh_degree_of(n_rest: int) -> int:
    """The SH degree d with (d + 1)² − 1 == ``n_rest`` higher coefficients; ValueError otherwise."""
    for degree in range(4):
        if (degree + 1) ** 2 - 1 == n_rest:
            return degree
    raise ValueError(f"{n_rest} higher-order coefficients per channel match no SH degree 0..3")


class GaussianModel(nn.Module):
    """Explicit 3D Gaussians that render through ``securegs_warp.rasterize``.

    Parameters (``nn.Parameter``, N rows each): ``means`` [N, 3], ``log_scales`` [N, 3], ``quats``
    [N, 4] (w first, not necessarily normalised), ``opacity_logits`` [N], ``features_dc`` [N, C],
    ``features_rest`` [N, R, C]. sh_degree: the largest SH degree (R = (d + 1)² − 1), or None for
    a raw C-channel field (R = 0): rendered colours are then ``features_dc`` unchanged.
    """

    def __init__(self, means, log_scales, quats, opacity_logits, features_dc, features_rest=None,
                 sh_degree: int | None = 3):
        super().__init__()
        n, c = means.shape[0], features_dc.shape[-1]
        rest_rows = 0 if sh_degree is None else (sh_degree + 1) ** 2 - 1
        if features_rest is None:
            features_rest = features_dc.new_zeros(n, rest_rows, c)
        shapes = {"means": (means, (n, 3)), "log_scales": (log_scales, (n, 3)), "quats": (quats, (n, 4)),
                  "opacity_logits": (opacity_logits, (n,)), "features_dc": (features_dc, (n, c)),
                  "features_rest": (features_rest, (n, rest_rows, c))}
        for name, (value, shape) in shapes.items():
            if tuple(value.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)} (sh_degree {sh_degree}), "
                                 f"got {list(value.shape)}")
            # A copy: the caller's tensor (a scene's point array, a checkpoint's) must not train along.
            setattr(self, name, nn.Parameter(value.detach().to(torch.float32).clone().contiguous()))
        self.sh_degree = sh_degree

    @classmethod
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor, sh_degree: int | None = 3) -> "GaussianModel":
        """3DGS's initialisation from a sparse point cloud: one Gaussian per point, isotropic with
        the root mean squared distance to its 3 nearest neighbours, identity rotation, opacity 0.1,
        the point's colour as the degree-0 coefficient (``colors`` [P, C]; raw when sh_degree is None)."""
        points = torch.as_tensor(points, dtype=torch.float32)
        colors = torch.as_tensor(colors, dtype=torch.float32, device=points.device)
        n = points.shape[0]
        dist = mean_sq_knn_distance(points).clamp_min(1e-7).sqrt()
        quats = torch.zeros(n, 4, device=points.device)
        quats[:, 0] = 1.0
        dc = colors if sh_degree is None else (colors - 0.5) / SH_C0
        return cls(points, torch.log(dist)[:, None].repeat(1, 3), quats,
                   inverse_sigmoid(torch.full((n,), INITIAL_OPACITY, device=points.device)), dc, sh_degree=sh_degree)

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def channels(self) -> int:
        return self.features_dc.shape[1]

    @property
    def device(self) -> torch.device:
        return self.means.device

    # -- rendering ------------------------------------------------------------------------------

    def colors(self, camera_center: torch.Tensor, sh_degree: int | None = None) -> torch.Tensor:
        """[N, C] colours seen from ``camera_center`` [3]: SH up to ``sh_degree`` (default the
        model's; 3DGS raises it during training) plus 0.5, clamped at 0, as 3DGS; the raw field
        when the model has no SH."""
        if self.sh_degree is None:
            return self.features_dc
        degree = self.sh_degree if sh_degree is None else min(sh_degree, self.sh_degree)
        coeffs = torch.cat([self.features_dc[:, None, :], self.features_rest[:, : (degree + 1) ** 2 - 1]], dim=1)
        if degree == 0:
            return (SH_C0 * coeffs[:, 0] + 0.5).clamp_min(0.0)
        # Not detached: 3DGS and gsplat send the view direction's gradient into the means too.
        dirs = torch.nn.functional.normalize(self.means - camera_center, dim=1)
        return ((sh_basis(degree, dirs)[:, :, None] * coeffs).sum(dim=1) + 0.5).clamp_min(0.0)

    def activated(self) -> dict:
        """The rasterizer's inputs: ``means`` [N, 3], ``quats`` [N, 4], ``scales`` [N, 3] (linear),
        ``opacities`` [N] (sigmoid)."""
        return {"means": self.means, "quats": self.quats, "scales": torch.exp(self.log_scales),
                "opacities": torch.sigmoid(self.opacity_logits)}

    def render(self, camera, options: RasterOptions | None = None, *, background: torch.Tensor | None = None,
               sh_degree: int | None = None, camera_index: int | None = None) -> dict:
        """Render one view: ``image`` [H, W, C], ``alpha`` [H, W, 1], ``info`` (rasterize's),
        ``gaussians`` (``activated()`` plus ``colors`` [N, C]). background: [C] or None (zeros).
        camera_index is accepted for the trainers' common interface and unused (no appearance codes)."""
        viewmat, K = camera_tensors(camera, self.device)
        g = {**self.activated(), "colors": self.colors(camera_center_from_viewmat(viewmat), sh_degree)}
        image, alpha, info = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], viewmat, K,
                                       camera.width, camera.height, background=background, options=options)
        return {"image": image, "alpha": alpha, "info": info, "gaussians": g}

    @torch.no_grad()
    def gaussians(self, camera, *, camera_index: int | None = None) -> dict:
        """Every Gaussian with its colour as seen from ``camera`` (for a degree-0 export)."""
        viewmat, _ = camera_tensors(camera, self.device)
        return {**self.activated(), "colors": self.colors(camera_center_from_viewmat(viewmat))}

    # -- densification row operations ----------------------------------------------------------

    @torch.no_grad()
    def keep_rows(self, keep: torch.Tensor, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Keep only the Gaussians where ``keep`` [N] bool is True (and their rows of Adam's moments)."""
        if keep.shape != (self.num_gaussians,) or keep.dtype != torch.bool:
            raise ValueError(f"keep must be a bool [{self.num_gaussians}] tensor, got {keep.dtype} {list(keep.shape)}")
        for name in GAUSSIAN_PARAM_NAMES:
            replace_parameter(self, name, getattr(self, name)[keep], optimizer, lambda moment: moment[keep])

    @torch.no_grad()
    def append_rows(self, rows: dict, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Append G Gaussians given as {parameter name: [G, ...] tensor} (every name in
        GAUSSIAN_PARAM_NAMES); Adam's moments get zero rows, as gsplat's duplicate and split do."""
        for name in GAUSSIAN_PARAM_NAMES:
            extra = rows[name].to(self.device, torch.float32)
            if extra.shape[1:] != getattr(self, name).shape[1:]:
                raise ValueError(f"new {name} rows must be [G, {list(getattr(self, name).shape[1:])}], "
                                 f"got {list(extra.shape)}")
            replace_parameter(self, name, torch.cat([getattr(self, name), extra]), optimizer,
                              lambda moment, extra=extra: torch.cat([moment, torch.zeros_like(extra)]))

    # -- files ----------------------------------------------------------------------------------

    def save(self, directory: str | os.PathLike) -> None:
        """Write ``directory/point_cloud.ply``: the standard 3DGS PLY (f_rest_* when sh_degree > 0)."""
        Path(directory).mkdir(parents=True, exist_ok=True)
        self.save_ply(Path(directory) / PLY_FILE)

    def save_ply(self, path: str | os.PathLike) -> None:
        write_gaussians_ply(path, self.means, self.quats, self.log_scales, self.opacity_logits, self.features_dc,
                            self.features_rest)

    @classmethod
    def load(cls, directory: str | os.PathLike, device="cpu", sh: bool = True) -> "GaussianModel":
        """Read a model folder written by :meth:`save` (or a 3DGS PLY path itself). sh: the f_dc
        columns are SH coefficients (3DGS; the degree follows from the f_rest count); False: a raw
        C-channel field, which must have no f_rest columns."""
        path = Path(directory)
        path = path / PLY_FILE if path.is_dir() else path
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no Gaussians PLY there")
        stored = read_gaussians_ply(path, device)
        n_rest = stored["features_rest"].shape[1]
        try:
            degree = sh_degree_of(n_rest) if sh else None
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        if not sh and n_rest:
            raise ValueError(f"{path}: a raw feature field has no f_rest_* columns, found {n_rest} per channel")
        return cls(**{name: stored[name] for name in GAUSSIAN_PARAM_NAMES}, sh_degree=degree)
