"""A SecureGS container on disk: the public release (exactly Scaffold-GS's files) and the key.

    OUT/public/      point_cloud.ply + opacity_mlp.pt, cov_mlp.pt, color_mlp.pt: nothing else
    OUT/key.safetensors  (or key.sealed with a passphrase): the private heads + JSON metadata,
                     bound to the release by a fingerprint of its public MLPs

The key's metadata holds everything ``reveal`` needs besides the release: the cameras (name, pose,
intrinsics, size) the hidden views are rendered from, which of them show the hidden payload, the
backgrounds and the rasterizer options. The key holder needs neither the training data nor the scene.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from ..config import from_dict
from ..data import Camera
from ..io import load_scaffold, save_scaffold
from ..keys import KeyFileError, container_fingerprint, load_key, save_key
from ..model import ScaffoldHeads
from ..rasterizer import RasterOptions
from .heads import PrivateHeads
from .model import SecureModel

PUBLIC_DIR = "public"
PLAIN_KEY, SEALED_KEY = "key.safetensors", "key.sealed"
_PREFIX = "private."


def release_fingerprint(heads: ScaffoldHeads) -> str:
    """Fingerprint of a release: its public MLP weights (unchanged by point-cloud degradations)."""
    return container_fingerprint({k: v.detach() for k, v in heads.state_dict().items()})


def save_container(out: str | Path, model: SecureModel, metadata: dict,
                   passphrase: str | None = None) -> tuple[Path, Path]:
    """Write the release (``out/public``) and the key; returns (public folder, key path).

    metadata: JSON-able dict stored in the key (see the module docstring for what reveal reads).
    """
    private = model.private
    if private is None:
        raise ValueError("a container needs the private heads: this model has no key")
    if private.decoder is not None and private.offset_mlp is None:
        raise ValueError("the w/o-HDGER ablation keeps explicit hidden offsets per anchor: it is a measurement "
                         "mode and cannot be released as a container")
    out = Path(out)
    public = out / PUBLIC_DIR
    save_scaffold(public, model.anchors, model.heads)
    key = out / (SEALED_KEY if passphrase else PLAIN_KEY)
    (out / (PLAIN_KEY if passphrase else SEALED_KEY)).unlink(missing_ok=True)  # no stale key of the other kind
    tensors = {_PREFIX + name: value.detach() for name, value in private.state_dict().items()}
    save_key(key, tensors, {**metadata, "heads": private.describe()}, release_fingerprint(model.heads), passphrase)
    return public, key


def open_container(public: str | Path, key: str | Path | None = None, passphrase: str | None = None,
                   device="cpu", check_fingerprint: bool = True) -> tuple[SecureModel, dict]:
    """Load a release and, with its key, the private heads: (model, the key's metadata). Without a
    key the model has ``private=None`` and the metadata is empty. A key for another release, a
    wrong passphrase or a modified key raise ``KeyFileError`` (never a garbage render).

    check_fingerprint=False opens a release whose public MLPs no longer match the key's fingerprint.
    Only two tools pass it: ``securegs attack``, because an attack that changes the MLP weights (a
    float16 round trip, fine-tuning) is meant to be scored with the key it was made against; and
    ``securegs verify``, which asks whether a release carries the key's message, so a release the key
    was not made for must get an answer ("absent", with its p-value), not a refusal. Any other user
    of a key is refused a release it was not made for. The key's own integrity is still checked."""
    anchors, heads = load_scaffold(public, device=device)
    if key is None:
        return SecureModel(anchors, heads, None), {}
    expected = release_fingerprint(heads) if check_fingerprint else None
    tensors, metadata = load_key(key, passphrase, expected_fingerprint=expected)
    if "bits" in metadata.get("heads", {}):
        raise KeyFileError(f"{key}: a key of an earlier securegs-warp, whose bit head was trained rather than derived "
                           "from the key; hide the payload again to get a key this version reads")
    try:
        private = PrivateHeads(heads, **metadata["heads"]).to(device)
        private.load_state_dict({name[len(_PREFIX):]: t.to(device) for name, t in tensors.items()})
    except (KeyError, TypeError, RuntimeError) as e:
        raise KeyFileError(f"{key}: the key's heads do not fit this release ({e})") from None
    return SecureModel(anchors, heads, private), metadata


@dataclasses.dataclass
class KeyViews:
    """What a key's metadata says about rendering (written by ``cli.secure.key_metadata``): the one
    reader of it, for reveal, audit and attack.

    cameras: every camera the key stores; hidden: those that show the hidden payload. raster: the
    rasterizer options. background, hidden_background: [3] colours (None: black). message: [L] 0/1
    int64, or None without bits.
    """

    cameras: list[Camera]
    hidden: list[Camera]
    raster: RasterOptions
    background: torch.Tensor | None
    hidden_background: torch.Tensor | None
    message: torch.Tensor | None

    @classmethod
    def from_metadata(cls, meta: dict, device) -> "KeyViews":
        cams = [Camera.from_record(r) for r in meta.get("cameras", [])]
        names = set(meta.get("hidden_views", []))
        colour = lambda v: None if v is None else torch.tensor(v, dtype=torch.float32, device=device)  # noqa: E731
        message = meta.get("heads", {}).get("message")  # the keyed bit decoder's message
        return cls(cams, [c for c in cams if c.name in names],
                   from_dict(RasterOptions, meta.get("raster", {}), "key raster options"),
                   colour(meta.get("background")), colour(meta.get("hidden_background")),
                   None if message is None else torch.tensor([int(b) for b in message], device=device))
