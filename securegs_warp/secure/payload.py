"""What is hidden: a 3D object (object or scene level), a whole scene, one image at one view, bits.

A payload spec is a string such as ``object``, ``scene``, ``image``, ``image:logo.png@3``,
``bits:48`` or a combination ``object+bits:48``. Objects and scenes come with the scene data (a
hidden view per camera); an image is a file, or ``builtin`` (a procedural emblem); bits are drawn
from the operating system's secure random source (not from the training seed, which config.json
records) or given literally (``bits:0b0110...``).

A release can hold several secrets, each behind its own key: their payloads are joined with
``,`` (``object+bits:48,bits:64,image``; ``parse_secrets``).
"""
from __future__ import annotations

import dataclasses
import secrets

import numpy as np
import torch

from ..data import SceneData
from ..data.cameras import read_image, resize_image

# λ of ℓ_total = ℓ_ori + λ·ℓ_hid: the paper's 10 for objects and 0.1 for one image; a whole hidden
# scene is as large as the cover, so it gets equal weight.
HIDDEN_WEIGHT = {"object": 10.0, "scene": 1.0, "image": 0.1}


@dataclasses.dataclass
class PayloadSpec:
    kind: str | None = None  # "object" | "scene" | "image" | None (bits only)
    image: str | None = None  # image payload: a file, or "builtin"
    image_view: int = 0  # image payload: the training view it is hidden at
    bits: int = 0
    bit_string: str | None = None

    @classmethod
    def parse(cls, text: str) -> "PayloadSpec":
        """Parse a payload string; anything ambiguous or unknown is refused with a ValueError.

        ``bits:L`` is L random bits (drawn when the payload is built); a literal message is written with a
        leading ``0b`` or a leading zero (``bits:0b1011``, ``bits:01101``), so that a length is never
        read as a message or the other way round. At most one of object, scene and image.
        """
        spec = cls()
        if not text.strip():
            raise ValueError(f"empty payload {text!r}")
        seen = set()
        for part in text.split("+"):
            name, _, arg = part.partition(":")
            if name in seen:
                raise ValueError(f"payload {text!r} names {name} twice")
            seen.add(name)
            if name in ("object", "scene", "image"):
                if spec.kind is not None:
                    raise ValueError(f"payload {text!r}: at most one of object, scene and image per container")
                if name == "image":
                    # The last @ starts the view: a file name may hold one of its own (me@2x.png@0).
                    path, at, view = (arg or "builtin").rpartition("@")
                    if not at:
                        path, view = view, ""
                    if not path:
                        raise ValueError(f"image payload {part!r}: the file name is empty")
                    if at and not view.isdigit():
                        raise ValueError(f"image payload {part!r}: the view after the last @ must be a training view "
                                         "index (a file name with an @ of its own takes one: FILE@0)")
                    spec.image, spec.image_view = path, int(view or 0)
                elif arg:
                    raise ValueError(f"payload {part!r}: {name} takes no argument")
                spec.kind = name
            elif name == "bits":
                spec.bits, spec.bit_string = _parse_bits(arg)
            else:
                raise ValueError(f"unknown payload {part!r}: use object, scene, image[:FILE[@VIEW]], "
                                 "bits[:L or :0bMESSAGE], joined with +")
        if spec.kind is None and spec.bits == 0:
            raise ValueError(f"empty payload {text!r}")
        return spec

    def describe(self) -> str:
        """The payload as a string ``parse`` reads back (a literal message is not repeated here: it is
        a secret of the key)."""
        parts = [self.kind if self.kind != "image" else f"image:{self.image}@{self.image_view}"] if self.kind else []
        return "+".join(parts + ([f"bits:{self.bits}"] if self.bits else []))


SECRET_SEPARATOR = ","


def parse_secrets(text: str) -> list[PayloadSpec]:
    """The payload of each secret of a release (``SECRET_SEPARATOR`` between them). A synthetic
    scene renders the hidden views of one object or scene, so at most one secret hides one."""
    specs = [PayloadSpec.parse(part) for part in text.split(SECRET_SEPARATOR)]
    if sum(spec.kind in ("object", "scene") for spec in specs) > 1:
        raise ValueError(f"payload {text!r}: at most one secret per release can hide an object or a scene (the "
                         "scene renders the hidden views of one); the others can hide images or bits")
    return specs


def describe_secrets(specs: list[PayloadSpec]) -> str:
    """The secrets' payloads as one string ``parse_secrets`` reads back (without literal messages)."""
    return SECRET_SEPARATOR.join(spec.describe() for spec in specs)


def recorded_payload(payload: str) -> str:
    """A payload as a run records it (config.json, checkpoints): a literal message by its length
    (``bits:0b1011`` -> ``bits:4``). The message itself is kept only in the key and the checkpoints'
    state, which a sealed run seals."""
    return describe_secrets(parse_secrets(payload))


def _parse_bits(arg: str) -> tuple[int, str | None]:
    """(length, literal message or None) of a ``bits`` argument (see ``PayloadSpec.parse``)."""
    literal = arg[2:] if arg.startswith("0b") else arg if arg.startswith("0") and len(arg) > 1 else None
    if literal is not None:
        if not literal or set(literal) - {"0", "1"}:
            raise ValueError(f"bits:{arg}: a literal message is made of 0s and 1s (e.g. bits:0b1011)")
        length = len(literal)
    elif not arg:
        length = 48
    elif arg.isdigit():
        length = int(arg)
    else:
        raise ValueError(f"bits:{arg}: give a length (bits:48) or a message (bits:0b1011)")
    if not 1 <= length <= 256:
        hint = f"; for the message {arg} write bits:0b{arg}" if set(arg) <= {"0", "1"} else ""
        raise ValueError(f"bits: length must be in [1, 256], got {length}{hint}")
    return length, literal


@dataclasses.dataclass
class Payload:
    """Training targets of the hidden branch, on the training device.

    views: hidden image [H, W, 3] per training camera (objects, scenes), or None.
    test_views: the same for the held-out cameras (for evaluation), or None.
    image_view / image: one training view and its hidden image [H, W, 3] (image payload), or None.
    bits: [L] float 0/1, or None. background: [3] colour behind the hidden render.
    weight: λ of the hidden image loss.
    """

    spec: PayloadSpec
    views: list | None
    test_views: list | None
    image_view: int | None
    image: torch.Tensor | None
    bits: torch.Tensor | None
    background: torch.Tensor
    weight: float

    @property
    def has_images(self) -> bool:
        return self.views is not None or self.image is not None


def builtin_emblem(height: int, width: int) -> np.ndarray:
    """A procedural copyright emblem [H, W, 3]: rings and a checkered cross on a warm field.

    Every feature is a fixed fraction of the image (the checker cell is 1/24 of its height, 4 px at
    96), so the emblem is the same picture, equally hard to hide, at every resolution."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    u, v = (x + 0.5) / width - 0.5, (y + 0.5) / height - 0.5
    r = np.hypot(u * width / height, v)
    rings = (np.sin(r * 60.0) > 0).astype(np.float32)
    cell = max(1, round(height / 24))
    cross = ((np.abs(u) < 0.06) | (np.abs(v) < 0.06)) & ((np.floor(x / cell) + np.floor(y / cell)) % 2 == 0)
    img = np.stack([0.9 - 0.5 * rings, 0.55 + 0.3 * rings, 0.2 + 0.2 * rings], axis=-1)
    img[cross] = (0.1, 0.1, 0.5)
    return np.clip(img, 0, 1).astype(np.float32)


def message_string(bits: torch.Tensor | None) -> str | None:
    """A message [L] of 0/1 values as the string of its bits ("0110..."), None for None."""
    return None if bits is None else "".join(str(int(b)) for b in bits.tolist())


def build_payload(spec: PayloadSpec, scene: SceneData, device) -> Payload:
    to = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=device)  # noqa: E731
    views = test_views = image = image_view = bits = None
    if spec.kind in ("object", "scene"):
        if scene.hidden_kind is None or any(c.hidden is None for c in scene.train):
            raise ValueError(f"payload {spec.kind!r} needs hidden views: scene {scene.name!r} has none "
                             "(synthetic: pass --hide OBJECT; real data: --hidden-dir)")
        views = [to(c.hidden) for c in scene.train]
        test_views = [to(c.hidden) for c in scene.test] if all(c.hidden is not None for c in scene.test) else None
    elif spec.kind == "image":
        if not 0 <= spec.image_view < len(scene.train):
            raise ValueError(f"image payload view {spec.image_view} is not a training view (0..{len(scene.train) - 1})")
        cam = scene.train[spec.image_view]
        raw = builtin_emblem(cam.height, cam.width) if spec.image == "builtin" else read_image(spec.image)[0]
        image, image_view = to(resize_image(raw, (cam.width, cam.height))), spec.image_view
    if spec.bits:
        if spec.bit_string:
            values = [int(b) for b in spec.bit_string]
        else:
            # A message derived from the run's seed could be recomputed from config.json.
            values = [secrets.randbits(1) for _ in range(spec.bits)]
        bits = to(values)
    background = scene.hidden_background if scene.hidden_background is not None else scene.background
    if spec.kind == "image" or background is None:
        background = scene.background if scene.background is not None else (0.0, 0.0, 0.0)
    return Payload(spec, views, test_views, image_view, image, bits, to(background),
                   HIDDEN_WEIGHT.get(spec.kind, 0.0))
