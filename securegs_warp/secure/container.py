"""A SecureGS container on disk: the public release (exactly Scaffold-GS's files) and a key per secret.

    OUT/public/      point_cloud.ply + opacity_mlp.pt, cov_mlp.pt, color_mlp.pt: nothing else
    OUT/key.safetensors  (or key.sealed with a passphrase, or where the caller puts it): one
                     secret's private heads + JSON metadata, bound to the release by a fingerprint of
                     its public MLPs; every further secret's key is a file of the same kind

The key's metadata holds everything ``reveal`` needs besides the release: the cameras (name, pose,
intrinsics, size) the hidden views are rendered from, which of them show the hidden payload, the
backgrounds and the rasterizer options. The key holder needs neither the training data nor the scene.
A key holds its own secret only: nothing in it names or describes the release's other secrets.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from ..config import from_dict
from ..data import Camera
from ..io import load_scaffold, save_scaffold
from ..keys import KeyFileError, container_fingerprint, load_key, save_key
from ..model import AnchorModel, ScaffoldHeads
from ..rasterizer import RasterOptions
from .heads import PrivateHeads
from .keyed_bits import KeyedBitDecoder
from .model import SecureModel
from .payload import PayloadSpec

PUBLIC_DIR = "public"
PLAIN_KEY, SEALED_KEY = "key.safetensors", "key.sealed"
_PREFIX = "private."


def default_key_path(folder: str | Path, passphrase: str | None) -> Path:
    """Where a key goes beside a release folder when no path is given: sealed or plain by name."""
    return Path(folder) / (SEALED_KEY if passphrase else PLAIN_KEY)


def remove_stale_key(folder: str | Path, passphrase: str | None) -> None:
    """Remove the default key of the other kind, so that a folder never holds a plain and a sealed
    key of two different runs."""
    default_key_path(folder, not passphrase).unlink(missing_ok=True)


def release_fingerprint(heads: ScaffoldHeads) -> str:
    """Fingerprint of a release: its public MLP weights (unchanged by point-cloud degradations)."""
    return container_fingerprint({k: v.detach() for k, v in heads.state_dict().items()})


@dataclasses.dataclass
class KeyFile:
    """One secret's key to write: metadata (JSON-able; see the module docstring for what reveal
    reads), path (None: OUT/key.safetensors, or OUT/key.sealed when sealed), passphrase (None: plain)."""

    metadata: dict
    path: Path | None = None
    passphrase: str | None = None


def save_container(out: str | Path, model: SecureModel, keys: list[KeyFile]) -> tuple[Path, list[Path]]:
    """Write the release (``out/public``) and one key per secret of ``model`` (``keys`` in the
    order of ``model.secrets``); returns (public folder, the key paths)."""
    if not len(model.secrets):
        raise ValueError("a container needs the private heads: this model has no key")
    if len(keys) != len(model.secrets):
        raise ValueError(f"the model holds {len(model.secrets)} secrets but {len(keys)} keys were given")
    for private in model.secrets:
        if private.decoder is not None and private.offset_mlp is None:
            raise ValueError("the w/o-HDGER ablation keeps explicit hidden offsets per anchor: it is a measurement "
                             "mode and cannot be released as a container")
    out = Path(out)
    public = out / PUBLIC_DIR
    paths = [Path(k.path) if k.path is not None else default_key_path(out, k.passphrase) for k in keys]
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError("two secrets' keys would be written to the same file: give each its own path")
    save_scaffold(public, model.anchors, model.heads)
    fingerprint = release_fingerprint(model.heads)
    for private, key, path in zip(model.secrets, keys, paths):
        if key.path is None:
            remove_stale_key(out, key.passphrase)
        tensors, described = private.key_state(model.anchors.xyz)
        save_key(path, {_PREFIX + name: value for name, value in tensors.items()},
                 {**key.metadata, "heads": described}, fingerprint, key.passphrase)
    return public, paths


def open_container(public: str | Path, key: str | Path | None = None, passphrase: str | None = None,
                   device="cpu", check_fingerprint: bool = True) -> tuple[SecureModel, dict]:
    """Load a release and, with its key, the private heads: (model, the key's metadata). Without a
    key the model has ``private=None`` and the metadata is empty. A key for another release, a
    wrong passphrase or a modified key raise ``KeyFileError`` (never a garbage render).

    check_fingerprint=False opens a release whose public MLPs no longer match the key's fingerprint.
    Only ``securegs attack`` passes it: an attack that changes the MLP weights (a float16 round trip,
    fine-tuning) is meant to be scored with the key it was made against. ``securegs verify`` asks
    whether any release carries the key's message and reads the bit decoder alone
    (``open_bit_decoder``). Any other user of a key is refused a release it was not made for. The
    key's own integrity is still checked."""
    anchors, heads = load_scaffold(public, device=device)
    if key is None:
        return SecureModel(anchors, heads, []), {}
    expected = release_fingerprint(heads) if check_fingerprint else None
    tensors, metadata = _load_readable_key(key, passphrase, expected)
    try:
        private = PrivateHeads(heads, **metadata["heads"]).to(device)
        private.load_state_dict({name[len(_PREFIX):]: t.to(device) for name, t in tensors.items()})
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise KeyFileError(f"{key}: the key's heads do not fit this release ({e})") from None
    return SecureModel(anchors, heads, [private]), metadata


def open_bit_decoder(public: str | Path, key: str | Path, passphrase: str | None = None,
                     device="cpu") -> tuple[AnchorModel, KeyedBitDecoder | None]:
    """A release's anchors and a key's bit decoder alone (None where the key hides no bits), for
    ``securegs verify``: the decoder is derived from the key's metadata for the release's feature
    width, so any Scaffold-GS release gets an answer, whatever its head options (its MLPs need not
    fit the key's hidden decoder). The key's integrity is checked; its fingerprint is not."""
    anchors, _ = load_scaffold(public, device=device)
    _, metadata = _load_readable_key(key, passphrase, None)
    described = metadata.get("heads", {})
    if "message" not in described:
        return anchors, None
    try:
        decoder = KeyedBitDecoder(anchors.feat.shape[1], described["message"], described["bit_seed"],
                                  described["bit_cell"])
    except (KeyError, TypeError, ValueError) as e:
        raise KeyFileError(f"{key}: the key's bit decoder cannot be derived from its metadata ({e})") from None
    return anchors, decoder.to(device)


def _load_readable_key(key: str | Path, passphrase: str | None, expected: str | None) -> tuple[dict, dict]:
    """``load_key``, refusing keys of earlier versions whose heads this one cannot rebuild."""
    tensors, metadata = load_key(key, passphrase, expected_fingerprint=expected)
    if "bits" in metadata.get("heads", {}):
        raise KeyFileError(f"{key}: a key of an earlier securegs-warp, whose bit head was trained rather than derived "
                           "from the key; hide the payload again to get a key this version reads")
    if "bit_seed" in metadata.get("heads", {}) and "bit_cell" not in metadata["heads"]:
        raise KeyFileError(f"{key}: a key of an earlier securegs-warp, whose bits were dealt by exact anchor positions; "
                           "hide the payload again to get a key this version reads")
    described = metadata.get("heads", {})
    if described.get("frame") == "box" and _PREFIX + "serving_radius" not in tensors:
        raise KeyFileError(f"{key}: a key of an earlier securegs-warp, whose serving anchors were counted rather than "
                           "bounded by a radius; hide the payload again to get a key this version reads")
    return tensors, metadata


@dataclasses.dataclass
class KeyViews:
    """What a key's metadata says about rendering (written by ``cli.secure.key_metadata``): the one
    reader of it, for reveal, audit and attack.

    cameras: every camera the key stores; hidden: those that show the hidden payload. raster: the
    rasterizer options. background, hidden_background: [3] colours (None: black). message: [L] 0/1
    int64, or None without bits. scene_targets: whether the scene's hidden views are this secret's
    targets (an object or a scene; an image secret's target is its image, even where another secret
    of the release makes the scene render an object).
    """

    cameras: list[Camera]
    hidden: list[Camera]
    raster: RasterOptions
    background: torch.Tensor | None
    hidden_background: torch.Tensor | None
    message: torch.Tensor | None
    scene_targets: bool = True

    @classmethod
    def from_metadata(cls, meta: dict, device) -> "KeyViews":
        cams = [Camera.from_record(r) for r in meta.get("cameras", [])]
        names = set(meta.get("hidden_views", []))
        colour = lambda v: None if v is None else torch.tensor(v, dtype=torch.float32, device=device)  # noqa: E731
        message = meta.get("heads", {}).get("message")  # the keyed bit decoder's message
        payload = meta.get("payload")
        scene_targets = payload is None or PayloadSpec.parse(payload).kind in ("object", "scene")
        return cls(cams, [c for c in cams if c.name in names],
                   from_dict(RasterOptions, meta.get("raster", {}), "key raster options"),
                   colour(meta.get("background")), colour(meta.get("hidden_background")),
                   None if message is None else torch.tensor([int(b) for b in message], device=device),
                   scene_targets)
