"""A SecureGS container on disk: the public release (exactly Scaffold-GS's files) and the key.

    OUT/public/      point_cloud.ply + opacity_mlp.pt, cov_mlp.pt, color_mlp.pt: nothing else
    OUT/key.safetensors  (or key.sealed with a passphrase): the private heads + JSON metadata,
                     bound to the release by a fingerprint of its public MLPs
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from ..io import load_scaffold, save_scaffold
from ..keys import container_fingerprint, load_key, save_key
from ..model import AnchorModel, ScaffoldHeads
from .heads import PrivateHeads

PUBLIC_DIR = "public"
PLAIN_KEY, SEALED_KEY = "key.safetensors", "key.sealed"
_PREFIX = "private."


def release_fingerprint(heads: ScaffoldHeads) -> str:
    """Fingerprint of a release: its public MLP weights (unchanged by point-cloud degradations)."""
    return container_fingerprint({k: v.detach() for k, v in heads.state_dict().items()})


def save_container(out: str | Path, model: AnchorModel, heads: ScaffoldHeads, private: PrivateHeads,
                   metadata: dict, passphrase: str | None = None) -> tuple[Path, Path]:
    """Write the release and the key; returns (public folder, key path)."""
    if private.decoder is not None and private.offset_mlp is None:
        raise ValueError("the w/o-HDGER ablation keeps explicit hidden offsets per anchor: it is a measurement "
                         "mode and cannot be released as a container")
    out = Path(out)
    public = out / PUBLIC_DIR
    save_scaffold(public, model, heads)
    key = out / (SEALED_KEY if passphrase else PLAIN_KEY)
    (out / (PLAIN_KEY if passphrase else SEALED_KEY)).unlink(missing_ok=True)  # no stale key of the other kind
    tensors = {_PREFIX + name: value.detach() for name, value in private.state_dict().items()}
    save_key(key, tensors, {**metadata, "heads": private.describe()}, release_fingerprint(heads), passphrase)
    return public, key


@dataclasses.dataclass
class Container:
    model: AnchorModel
    heads: ScaffoldHeads
    private: PrivateHeads | None  # None: opened without the key
    metadata: dict


def open_container(public: str | Path, key: str | Path | None = None, passphrase: str | None = None,
                   device="cpu") -> Container:
    """Load a release and, with its key, the private heads. A key for another release, a wrong
    passphrase or a modified key raise ``KeyFileError`` (never a garbage render)."""
    model, heads = load_scaffold(public, device=device)
    if key is None:
        return Container(model, heads, None, {})
    tensors, metadata = load_key(key, passphrase, expected_fingerprint=release_fingerprint(heads))
    private = PrivateHeads(heads, **metadata["heads"]).to(device)
    private.load_state_dict({name[len(_PREFIX):]: t.to(device) for name, t in tensors.items()})
    return Container(model, heads, private, metadata)
