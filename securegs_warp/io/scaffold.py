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
``feature_bank_mlp.pt`` and ``embedding_appearance.pt``, written as Scaffold-GS's
``GaussianModel.save_mlp_checkpoints(mode='split')`` writes them (scene/gaussian_model.py of
city-super/Scaffold-GS): each is ``torch.jit.trace`` of the module in eval mode with an example
input of Scaffold-GS's shape ([1, d+3(+1)] opacity and covariance, [1, d+3(+1)+A] colour, [1, 4]
feature bank, a [1] long index for the embedding), saved with ``torch.jit.save``. Scaffold-GS's
``load_mlp_checkpoints`` opens them with ``torch.jit.load``, so a folder written here renders in
Scaffold-GS as it is. Tracing happens on a CPU copy, so the caller's module keeps its device,
training mode and parameters.

Reading never executes anything from a file: a TorchScript archive (ours or Scaffold-GS's) is read
by :mod:`.torchscript`, which interprets its ``data.pkl`` symbolically and takes the tensors from
the raw storage records, never calling ``torch.jit.load`` or unpickling it. Plain state-dict files
(``torch.save(state_dict)``, what this package wrote before) and Scaffold-GS's ``mode='unite'``
file ``checkpoints.pth`` (a dict of the MLPs' state dicts) are read with
``torch.load(weights_only=True)``, which only rebuilds tensors and containers.
"""

from __future__ import annotations

import copy
import io
import os
import re
import warnings
import zipfile
from pathlib import Path

import torch
from torch import nn

from ..model.anchors import AnchorModel
from ..model.heads import ScaffoldHeads
from .atomic import atomic_folder, atomic_write
from .gs_ply import PlyFormatError, read_vertex_ply, vertex_columns, write_vertex_ply
from .torchscript import TorchScriptError, archive_kind, read_torchscript_state_dict

POINT_CLOUD_FILE = "point_cloud.ply"
MLP_FILES = {
    "opacity_mlp": "opacity_mlp.pt",
    "cov_mlp": "cov_mlp.pt",
    "color_mlp": "color_mlp.pt",
    "feature_bank_mlp": "feature_bank_mlp.pt",
    "embedding_appearance": "embedding_appearance.pt",
}
"""ScaffoldHeads attribute -> file name beside point_cloud.ply."""
UNITE_FILE = "checkpoints.pth"
"""Scaffold-GS's ``save_mlp_checkpoints(mode='unite')`` file: all MLP state dicts in one dict."""
UNITE_KEYS = {
    "opacity_mlp": "opacity_mlp",
    "cov_mlp": "cov_mlp",
    "color_mlp": "color_mlp",
    "feature_bank_mlp": "feature_bank_mlp",
    "appearance": "embedding_appearance",
}
"""Key in ``checkpoints.pth`` -> ScaffoldHeads attribute."""
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
    """Write ``point_cloud.ply`` and the heads' MLP files as the folder ``directory``, in one unit.

    The MLPs are TorchScript archives traced as Scaffold-GS's ``save_mlp_checkpoints`` traces them
    (see the module docstring), so Scaffold-GS's ``load_mlp_checkpoints`` opens them. ``heads`` is
    not modified: each module is traced from a CPU copy in eval mode.

    The folder holds exactly the release's files. It is built beside ``directory`` under a hidden
    name and swapped in whole (:func:`.atomic.atomic_folder`): an interrupted save, a crash or
    ``kill -9`` included, leaves the complete previous folder or the complete new one, never new
    MLPs beside an old point cloud; at most a hidden ``.<name>.tmp-*`` / ``.<name>.old-*`` sibling
    stays, which the next save of ``directory`` removes and loaders never read. The old folder is
    replaced, not edited, so a folder that holds anything besides a release's files is refused
    rather than emptied.

    Raises:
        FileExistsError: ``directory`` holds a file that is not part of a Scaffold-GS release
            (named); nothing is written.
        NotADirectoryError: ``directory`` is a file.
    """
    directory = Path(directory)
    _refuse_foreign_content(directory)
    archives = {
        filename: traced_mlp_bytes(getattr(heads, attribute), _example_input(heads, attribute))
        for attribute, filename in MLP_FILES.items()
        if getattr(heads, attribute) is not None
    }
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
    values = values.detach().cpu().numpy()
    with atomic_folder(directory) as folder:
        for filename, archive in archives.items():
            atomic_write(folder / filename, lambda f, archive=archive: f.write(archive))
        write_vertex_ply(folder / POINT_CLOUD_FILE, anchor_ply_properties(model.n_offsets, model.feat_dim), values)


# What a folder written by save_scaffold may hold: a release's files, Scaffold-GS's unite file and the
# hidden temporary files of an interrupted atomic_write (from saves that wrote file by file).
_RELEASE_NAMES = frozenset([POINT_CLOUD_FILE, UNITE_FILE, *MLP_FILES.values()])
_STRAY_TEMP_FILE = re.compile(r"\.(.+)\.[0-9a-f]{32}\.tmp")


def _refuse_foreign_content(directory: Path) -> None:
    """Raise if replacing ``directory`` would delete something that is not part of a release."""
    try:
        names = sorted(os.listdir(directory))
    except (FileNotFoundError, NotADirectoryError):
        return
    for name in names:
        stray = _STRAY_TEMP_FILE.fullmatch(name)
        if name in _RELEASE_NAMES or (stray and stray.group(1) in _RELEASE_NAMES):
            continue
        raise FileExistsError(
            f"{directory}: holds {name!r}, which is not part of a Scaffold-GS release; saving replaces "
            "the whole folder, so move it away or save elsewhere"
        )


def _example_input(heads: ScaffoldHeads, attribute: str) -> torch.Tensor:
    """The example input of Scaffold-GS's save_mlp_checkpoints for that module (shape and dtype).

    Scaffold-GS uses ``torch.rand``; the values do not change what is traced (no data-dependent
    branches), and zeros keep saving from drawing on the global random stream.
    """
    d, a = heads.feat_dim, heads.appearance_dim
    widths = {
        "opacity_mlp": d + 3 + int(heads.add_opacity_dist),
        "cov_mlp": d + 3 + int(heads.add_cov_dist),
        "color_mlp": d + 3 + int(heads.add_color_dist) + a,
        "feature_bank_mlp": 3 + 1,
    }
    if attribute == "embedding_appearance":
        return torch.zeros((1,), dtype=torch.long)
    return torch.zeros(1, widths[attribute])


def traced_mlp_bytes(module: nn.Module, example_input: torch.Tensor) -> bytes:
    """``torch.jit.save`` bytes of ``torch.jit.trace`` of a CPU copy of ``module`` in eval mode."""
    copied = copy.deepcopy(module).cpu()
    copied.eval()
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # torch.jit is deprecated in recent torch, but it is the format Scaffold-GS reads.
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.", category=DeprecationWarning)
        torch.jit.save(torch.jit.trace(copied, example_input), buffer)
    return buffer.getvalue()


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

    The MLPs are read from the split files (``opacity_mlp.pt`` ...) with :func:`load_weights`;
    when none of them exists but ``checkpoints.pth`` (Scaffold-GS's ``mode='unite'``) does, from
    that file.

    A release is checked before it is used, so that a damaged one fails instead of decoding to
    garbage: at least one anchor, every anchor attribute finite, counts and shapes that agree, every
    MLP weight finite. Hidden siblings that an interrupted :func:`save_scaffold` may leave are not
    read.

    Raises:
        PlyFormatError: point_cloud.ply is unreadable, has no anchors, lacks a property (named), has
            inconsistent counts, or holds NaN or inf (naming the attribute group and how many anchors).
        MlpFileError: an MLP file is unsafe to load, unreadable, its shapes do not fit the anchors,
            or a weight is NaN or inf (naming the tensor).
        FileNotFoundError: a required file is missing.
    """
    directory = Path(directory)
    if not (directory / POINT_CLOUD_FILE).is_file():
        raise FileNotFoundError(f"{directory}: not a Scaffold-GS release (no {POINT_CLOUD_FILE} there; a run folder "
                                "holds its release in model/ after `securegs train`, public/ after `securegs hide`)")
    model = _load_anchors(directory / POINT_CLOUD_FILE, voxel_size).to(device)
    d, k = model.feat_dim, model.n_offsets

    weights = _load_mlps(directory, device)

    appearance_dim = num_cameras = 0
    if "embedding_appearance" in weights:
        path, state = weights["embedding_appearance"]
        weights["embedding_appearance"] = (path, _embedding_state(path, state))
        num_cameras, appearance_dim = weights["embedding_appearance"][1]["weight"].shape
    if "feature_bank_mlp" in weights and d % 4 != 0:
        raise MlpFileError(weights["feature_bank_mlp"][0], f"a feature bank splits the feature in 4, but the "
                                                           f"anchors' feature dimension is {d}")
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


def _load_mlps(directory: Path, device: torch.device | str) -> dict[str, tuple[str | Path, dict]]:
    """ScaffoldHeads attribute -> (file, state dict) for the MLP files present."""
    unite = directory / UNITE_FILE
    if unite.exists() and not any((directory / MLP_FILES[a]).exists() for a in _REQUIRED_MLPS):
        return _load_unite(unite, device)
    weights = {}
    for attribute, filename in MLP_FILES.items():
        path = directory / filename
        if path.exists():
            weights[attribute] = (path, load_weights(path, device))
        elif attribute in _REQUIRED_MLPS:
            raise FileNotFoundError(f"{path}: Scaffold-GS model folder has no {filename}")
    return weights


def _load_unite(path: Path, device: torch.device | str) -> dict[str, tuple[str, dict]]:
    """The state dicts in a ``checkpoints.pth``, each named ``checkpoints.pth['key']`` in errors."""
    content = _torch_load_tensors(path, device)
    if not isinstance(content, dict):
        raise MlpFileError(path, "expected a dict of state dicts (Scaffold-GS's checkpoints.pth)")
    unknown = sorted(str(key) for key in content if key not in UNITE_KEYS)
    if unknown:
        raise MlpFileError(path, f"unexpected entry {unknown[0]!r}; expected some of {sorted(UNITE_KEYS)}")
    weights = {}
    for key, attribute in UNITE_KEYS.items():
        name = f"{os.fspath(path)}[{key!r}]"
        if key in content:
            weights[attribute] = (name, _check_state_dict(name, content[key]))
        elif attribute in _REQUIRED_MLPS:
            raise MlpFileError(path, f"has no {key!r} entry")
    return weights


def _load_anchors(path: Path, voxel_size: float | None) -> AnchorModel:
    vertex = read_vertex_ply(path)
    if vertex.count == 0:
        raise PlyFormatError(path, "has no anchors (its vertex element is empty)")
    names = {p.name for p in vertex.properties}
    n_offset_values = _count_indexed(path, names, "f_offset_")
    feat_dim = _count_indexed(path, names, "f_anchor_feat_")
    if n_offset_values == 0 or n_offset_values % 3 != 0:
        raise PlyFormatError(path, f"has {n_offset_values} f_offset_* properties; expected 3k with k >= 1")
    if feat_dim == 0:
        raise PlyFormatError(path, "has no f_anchor_feat_* properties")
    k = n_offset_values // 3
    values = torch.from_numpy(vertex_columns(path, vertex, anchor_ply_properties(k, feat_dim)))
    groups = dict(zip(_ANCHOR_GROUPS, values.split([3, 3, 3 * k, feat_dim, 1, 6, 4], dim=1)))
    for group, columns in groups.items():
        if group == "nx/ny/nz":
            continue  # written as zeros and never read, by Scaffold-GS as here
        bad = ~torch.isfinite(columns).all(dim=1)
        if bad.any():
            raise PlyFormatError(path, f"{group} holds NaN or inf in {int(bad.sum())} of {len(bad)} anchors "
                                       f"(the first is anchor {int(bad.nonzero()[0])})")
    return AnchorModel(
        xyz=groups["x/y/z"],
        feat=groups["f_anchor_feat_*"],
        offsets=groups["f_offset_*"].reshape(-1, 3, k).transpose(1, 2),
        scaling=groups["scale_*"],
        rotation=groups["rot_*"],
        opacity=groups["opacity"],
        voxel_size=voxel_size,
    )


# The property groups of point_cloud.ply, in file order, as errors name them.
_ANCHOR_GROUPS = ("x/y/z", "nx/ny/nz", "f_offset_*", "f_anchor_feat_*", "opacity", "scale_*", "rot_*")


def _count_indexed(path: Path, names: set[str], prefix: str) -> int:
    """Number of properties ``prefix0, prefix1, ...``; they must be numbered 0..n-1 without gaps."""
    indices = sorted(int(n[len(prefix):]) for n in names if n.startswith(prefix) and n[len(prefix):].isdigit())
    if indices != list(range(len(indices))):
        missing = sorted(set(range(max(indices) + 1)) - set(indices))
        raise PlyFormatError(path, f"vertex property '{prefix}{missing[0]}' is missing")
    return len(indices)


def _embedding_state(path: str | Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Our embedding file holds ``weight``; Scaffold-GS's wraps nn.Embedding as ``embedding.weight``."""
    for key in ("weight", "embedding.weight"):
        if key in state and state[key].ndim == 2:
            if 0 in state[key].shape:
                raise MlpFileError(path, f"'{key}' has shape {list(state[key].shape)}; an appearance embedding "
                                         "needs at least one camera and one channel")
            return {"weight": state[key]}
    raise MlpFileError(path, f"no 2-D 'weight' or 'embedding.weight' tensor among {sorted(state)}")


def _extra_inputs(entry: tuple[str | Path, dict[str, torch.Tensor]], base: int) -> int:
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


def _load_into(module: nn.Module, state: dict[str, torch.Tensor], path: str | Path, d: int, k: int) -> None:
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    if missing:
        raise MlpFileError(path, f"tensor '{missing[0]}' is missing (has {sorted(state)})")
    for key, tensor in expected.items():
        if state[key].shape != tensor.shape:
            raise MlpFileError(path, f"'{key}' has shape {list(state[key].shape)}, expected {list(tensor.shape)} "
                                     f"for feature dimension {d} and {k} offsets per anchor")
        # Cast first: a float64 weight beyond float32's range would load as inf.
        value = state[key].to(tensor.dtype)
        if value.is_floating_point():
            bad = int((~torch.isfinite(value)).sum())
            if bad:
                raise MlpFileError(path, f"'{key}' holds NaN or inf in {bad} of {value.numel()} values")
    module.load_state_dict({key: state[key] for key in expected})


# ----------------------------------------------------------------------------------------------
# Reading weights without executing code
# ----------------------------------------------------------------------------------------------


def load_weights(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """The named tensors of a weights file, read without running any code from it.

    Accepts a TorchScript archive (``torch.jit.save``, how Scaffold-GS and this package save the
    MLPs), whose tensors :func:`.torchscript.read_torchscript_state_dict` takes from the archive's
    records without ``torch.jit.load`` and without unpickling it; and a ``torch.save``-d dict of
    tensors, read with ``torch.load(weights_only=True)``. Anything else is refused.

    Raises:
        MlpFileError: naming the file and why it was refused.
    """
    path = Path(path)
    kind = archive_kind(path)
    if kind == "torchscript":
        try:
            state = read_torchscript_state_dict(path)
        except TorchScriptError as e:
            raise MlpFileError(path, f"TorchScript archive refused: {e}") from e
        return _check_state_dict(path, {key: value.to(device) for key, value in state.items()})
    if kind == "zip":
        raise MlpFileError(path, "is a zip archive but neither a TorchScript archive (torch.jit.save) nor a "
                                 "torch.save file (no single '<folder>/data.pkl' record)")
    return _check_state_dict(path, _torch_load_tensors(path, device))


def _torch_load_tensors(path: Path, device: torch.device | str):
    try:
        return torch.load(path, weights_only=True, map_location=device)
    except _UNPICKLING_ERRORS as e:
        raise MlpFileError(
            path,
            f"refused by torch.load(weights_only=True): it is not plain tensors, and unpickling it could "
            f"run code ({e})",
        ) from e
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile) as e:  # a truncated zip: OSError(EINVAL)
        raise MlpFileError(path, f"not a readable torch weights file ({e})") from e


def _check_state_dict(path: str | os.PathLike, state) -> dict[str, torch.Tensor]:
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise MlpFileError(path, "expected a dict of named tensors (a state_dict)")
    return dict(state)
