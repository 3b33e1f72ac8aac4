"""Scaffold-GS model folders: ``point_cloud.ply`` (the anchors) and the MLP files beside it.

``point_cloud.ply`` has one ``vertex`` per anchor with the float32 properties, in this order::

    x y z nx ny nz                     anchor position, zero normals
    f_offset_0 .. f_offset_{3k-1}      offsets [N, k, 3] stored coordinate-major: all k x, all k y,
                                       all k z (Scaffold-GS writes offsets.transpose(1, 2).flatten(1))
    f_anchor_feat_0 .. _{d-1}          feature
    opacity                            opacity logit
    scale_0 .. scale_5                 log scalings
    rot_0 .. rot_3                     quaternion, w first

The MLPs are ``opacity_mlp.pt``, ``cov_mlp.pt``, ``color_mlp.pt`` and, when used,
``feature_bank_mlp.pt`` and ``embedding_appearance.pt``. Scaffold-GS writes them with
``torch.jit.trace(...).save()``; loading those with ``torch.jit.load`` would execute code from the
file. We write plain state dicts (``torch.save(state_dict)``) and read them only with
``torch.load(weights_only=True)``; TorchScript archives are refused with the one-line conversion.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import torch
from torch import nn

from ..model.anchors import AnchorModel
from ..model.heads import ScaffoldHeads
from .atomic import atomic_write
from .gs_ply import PlyFormatError, read_vertex_ply, vertex_columns, write_vertex_ply

POINT_CLOUD_FILE = "point_cloud.ply"
MLP_FILES = {
    "opacity_mlp": "opacity_mlp.pt",
    "cov_mlp": "cov_mlp.pt",
    "color_mlp": "color_mlp.pt",
    "feature_bank_mlp": "feature_bank_mlp.pt",
    "embedding_appearance": "embedding_appearance.pt",
}
"""ScaffoldHeads attribute -> file name beside point_cloud.ply."""
_REQUIRED_MLPS = ("opacity_mlp", "cov_mlp", "color_mlp")
# What torch.load(weights_only=True) raises for a file holding anything but tensors.
_UNPICKLING_ERRORS = (torch.serialization.pickle.UnpicklingError,)


class MlpFileError(ValueError):
    """An MLP file is unsafe, unreadable or does not fit the anchors. Names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def anchor_ply_properties(n_offsets: int, feat_dim: int) -> list[str]:
    """The property names of point_cloud.ply, in file order, for k offsets and d feature channels."""
    return (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_offset_{i}" for i in range(3 * n_offsets)]
        + [f"f_anchor_feat_{i}" for i in range(feat_dim)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(6)]
        + [f"rot_{i}" for i in range(4)]
    )


# ----------------------------------------------------------------------------------------------
# Saving
# ----------------------------------------------------------------------------------------------


def save_scaffold(directory: str | os.PathLike, model: AnchorModel, heads: ScaffoldHeads) -> None:
    """Write ``point_cloud.ply`` and the heads' MLP files into ``directory`` (created if needed).

    Each file is written atomically; the MLPs go first, so an interrupted save never leaves a new
    point cloud next to missing MLPs (it can leave new MLPs beside an older point cloud).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for attribute, filename in MLP_FILES.items():
        module = getattr(heads, attribute)
        if module is None:
            # A stale optional file from an earlier save would change what load_scaffold builds.
            (directory / filename).unlink(missing_ok=True)
            continue
        state = {key: value.detach().cpu() for key, value in module.state_dict().items()}
        atomic_write(directory / filename, lambda f, state=state: torch.save(state, f))

    n = model.num_anchors
    with torch.no_grad():
        values = torch.cat(
            [
                model.xyz,
                torch.zeros_like(model.xyz),
                model.offsets.transpose(1, 2).reshape(n, -1),
                model.feat,
                model.opacity,
                model.scaling,
                model.rotation,
            ],
            dim=1,
        )
    write_vertex_ply(directory / POINT_CLOUD_FILE, anchor_ply_properties(model.n_offsets, model.feat_dim),
                     values.detach().cpu().numpy())


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------


def load_scaffold(
    directory: str | os.PathLike,
    device: torch.device | str = "cpu",
    voxel_size: float | None = None,
) -> tuple[AnchorModel, ScaffoldHeads]:
    """Read a Scaffold-GS model folder (ours or Scaffold-GS's own) into anchors and heads.

    k and d come from the PLY header (the ``f_offset_*`` and ``f_anchor_feat_*`` counts); the heads'
    options (feature bank, appearance embedding and its size, distance inputs) from which MLP files
    exist and their shapes. ``voxel_size`` is not stored by Scaffold-GS; pass it to grow anchors.

    Raises:
        PlyFormatError: point_cloud.ply lacks a property (named) or has inconsistent counts.
        MlpFileError: an MLP file is unsafe to load, unreadable, or its shapes do not fit.
        FileNotFoundError: a required file is missing.
    """
    directory = Path(directory)
    model = _load_anchors(directory / POINT_CLOUD_FILE, voxel_size).to(device)
    d, k = model.feat_dim, model.n_offsets

    weights = {}
    for attribute, filename in MLP_FILES.items():
        path = directory / filename
        if path.exists():
            weights[attribute] = (path, load_weights(path, device))
        elif attribute in _REQUIRED_MLPS:
            raise FileNotFoundError(f"{path}: Scaffold-GS model folder has no {filename}")

    appearance_dim = num_cameras = 0
    if "embedding_appearance" in weights:
        path, state = weights["embedding_appearance"]
        weights["embedding_appearance"] = (path, _embedding_state(path, state))
        num_cameras, appearance_dim = weights["embedding_appearance"][1]["weight"].shape
    heads = ScaffoldHeads(
        d, k,
        use_feat_bank="feature_bank_mlp" in weights,
        appearance_dim=appearance_dim,
        num_cameras=num_cameras,
        add_opacity_dist=_extra_inputs(weights["opacity_mlp"], d + 3) == 1,
        add_cov_dist=_extra_inputs(weights["cov_mlp"], d + 3) == 1,
        add_color_dist=_extra_inputs(weights["color_mlp"], d + 3 + appearance_dim) == 1,
    ).to(device)
    for attribute, (path, state) in weights.items():
        _load_into(getattr(heads, attribute), state, path, d, k)
    return model, heads


def _load_anchors(path: Path, voxel_size: float | None) -> AnchorModel:
    vertex = read_vertex_ply(path)
    names = {p.name for p in vertex.properties}
    n_offset_values = _count_indexed(path, names, "f_offset_")
    feat_dim = _count_indexed(path, names, "f_anchor_feat_")
    if n_offset_values == 0 or n_offset_values % 3 != 0:
        raise PlyFormatError(path, f"has {n_offset_values} f_offset_* properties; expected 3k with k >= 1")
    if feat_dim == 0:
        raise PlyFormatError(path, "has no f_anchor_feat_* properties")
    k = n_offset_values // 3
    values = torch.from_numpy(vertex_columns(path, vertex, anchor_ply_properties(k, feat_dim)))
    xyz, _normals, offsets, feat, opacity, scaling, rotation = values.split([3, 3, 3 * k, feat_dim, 1, 6, 4], dim=1)
    return AnchorModel(
        xyz=xyz,
        feat=feat,
        offsets=offsets.reshape(-1, 3, k).transpose(1, 2),
        scaling=scaling,
        rotation=rotation,
        opacity=opacity,
        voxel_size=voxel_size,
    )


def _count_indexed(path: Path, names: set[str], prefix: str) -> int:
    """Number of properties ``prefix0, prefix1, ...``; they must be numbered 0..n-1 without gaps."""
    indices = sorted(int(n[len(prefix):]) for n in names if n.startswith(prefix) and n[len(prefix):].isdigit())
    if indices != list(range(len(indices))):
        missing = sorted(set(range(max(indices) + 1)) - set(indices))
        raise PlyFormatError(path, f"vertex property '{prefix}{missing[0]}' is missing")
    return len(indices)


def _embedding_state(path: Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Our embedding file holds ``weight``; Scaffold-GS's wraps nn.Embedding as ``embedding.weight``."""
    for key in ("weight", "embedding.weight"):
        if key in state and state[key].ndim == 2:
            return {"weight": state[key]}
    raise MlpFileError(path, f"no 2-D 'weight' or 'embedding.weight' tensor among {sorted(state)}")


def _extra_inputs(entry: tuple[Path, dict[str, torch.Tensor]], base: int) -> int:
    """How many inputs the first Linear takes beyond ``base`` (1 when the distance is fed)."""
    path, state = entry
    weight = state.get("0.weight")
    if weight is None or weight.ndim != 2:
        raise MlpFileError(path, f"no 2-D '0.weight' tensor among {sorted(state)}")
    extra = weight.shape[1] - base
    if extra not in (0, 1):
        raise MlpFileError(path, f"first layer takes {weight.shape[1]} inputs; expected {base} or {base + 1} "
                                 "for the anchors' feature dimension")
    return extra


def _load_into(module: nn.Module, state: dict[str, torch.Tensor], path: Path, d: int, k: int) -> None:
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    if missing:
        raise MlpFileError(path, f"tensor '{missing[0]}' is missing (has {sorted(state)})")
    for key, tensor in expected.items():
        if state[key].shape != tensor.shape:
            raise MlpFileError(path, f"'{key}' has shape {list(state[key].shape)}, expected {list(tensor.shape)} "
                                     f"for feature dimension {d} and {k} offsets per anchor")
    module.load_state_dict({key: state[key] for key in expected})


# ----------------------------------------------------------------------------------------------
# Reading weights without executing code
# ----------------------------------------------------------------------------------------------


def load_weights(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """The named tensors of a weights file, read without running any code from it.

    Accepts a ``torch.save``-d dict of tensors, read with ``torch.load(weights_only=True)``. A
    TorchScript archive (how the original Scaffold-GS saves its MLPs) is refused: its tensors can
    only be reached by unpickling the archive, and no file is ever unpickled here. The error says
    how to convert it once, where the file is trusted.
    """
    path = Path(path)
    if _is_torchscript_archive(path):
        raise MlpFileError(
            path,
            "is a TorchScript archive (the original Scaffold-GS saves MLPs with torch.jit); reading it would "
            "mean unpickling the file, which securegs never does. Convert it once where you trust it: "
            f"python -c \"import torch; torch.save(torch.jit.load('{path}').state_dict(), '{path}')\"",
        )
    try:
        state = torch.load(path, weights_only=True, map_location=device)
    except _UNPICKLING_ERRORS as e:
        raise MlpFileError(
            path,
            f"refused by torch.load(weights_only=True): it is not plain tensors, and unpickling it could "
            f"run code ({e})",
        ) from e
    except (RuntimeError, EOFError, zipfile.BadZipFile) as e:
        raise MlpFileError(path, f"not a readable torch weights file ({e})") from e
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise MlpFileError(path, "expected a dict of named tensors (a state_dict)")
    return state


def _is_torchscript_archive(path: Path) -> bool:
    # torch.jit.save archives carry constants.pkl; torch.save archives never do (the test torch
    # itself uses to tell them apart).
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as archive:
        return any(name.endswith("/constants.pkl") for name in archive.namelist())


