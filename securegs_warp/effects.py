"""Effects on demand: one object that names every optional stage of a render or a training run.

A scene and a render request declare what they need; the trainer builds only those heads and the
rasterizer compiles only those kernel variants (``RasterOptions`` flags), so an effect that is off
costs nothing. ``infer_scene_effects`` reads what a ``SceneData`` (and a payload) asks for;
``Effects.for_request`` narrows that to one render (a public render never runs a private branch, an
RGB-only render writes no depth).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

DEPTH_MODES = (None, "accumulated", "expected")
HIDDEN_BRANCHES = frozenset({"object", "image", "bits", "scene"})


@dataclasses.dataclass(frozen=True)
class Effects:
    """Every optional effect of a Scaffold-GS / SecureGS render.

    antialiased: the rasterizer's antialiased (Mip-Splatting style) opacity compensation.
    depth: None, "accumulated" or "expected" (a fourth output channel from the rasterizer).
    background: (3,) colour tuple composited under the image, or None (no compositing, which equals
        a black background).
    feature_bank, appearance_dim (with num_cameras), opacity/cov/color_dist: the Scaffold-GS head
        inputs (``ScaffoldHeads``).
    hidden: the SecureGS private branches to build, a subset of {"object", "image", "bits", "scene"}.
    """

    antialiased: bool = False
    depth: str | None = None
    background: tuple[float, float, float] | None = None
    feature_bank: bool = False
    appearance_dim: int = 0
    num_cameras: int = 0
    opacity_dist: bool = False
    cov_dist: bool = False
    color_dist: bool = False
    hidden: frozenset = frozenset()

    def __post_init__(self):
        if self.depth not in DEPTH_MODES:
            raise ValueError(f"depth must be one of {DEPTH_MODES}, got {self.depth!r}")
        if self.appearance_dim < 0:
            raise ValueError(f"appearance_dim must be >= 0, got {self.appearance_dim}")
        if self.appearance_dim > 0 and self.num_cameras <= 0:
            raise ValueError("the appearance effect needs the number of training cameras (num_cameras > 0)")
        object.__setattr__(self, "hidden", frozenset(self.hidden))
        unknown = self.hidden - HIDDEN_BRANCHES
        if unknown:
            raise ValueError(f"unknown hidden branches {sorted(unknown)}; known: {sorted(HIDDEN_BRANCHES)}")
        if len(self.hidden - {"bits"}) > 1:
            raise ValueError(f"at most one hidden object/image/scene branch, got {sorted(self.hidden - {'bits'})}")
        if self.background is not None:
            bg = tuple(float(c) for c in np.asarray(self.background, dtype=np.float32).reshape(-1))
            if len(bg) != 3:
                raise ValueError(f"background must be 3 values (RGB), got {len(bg)}")
            object.__setattr__(self, "background", bg)

    # --- narrowing -----------------------------------------------------------------------------
    def for_request(self, *, private: bool = False, depth: bool | str = False) -> "Effects":
        """The effects one render needs: private=False drops every hidden branch; depth=False drops
        depth output (depth=True keeps the scene's mode, or "accumulated"; a string picks the mode)."""
        mode = (self.depth or "accumulated") if depth is True else (depth or None)
        return dataclasses.replace(self, hidden=self.hidden if private else frozenset(), depth=mode)

    # --- what each stage reads -------------------------------------------------------------------
    def raster_options(self) -> dict:
        """Keyword arguments of ``rasterize`` for the flags that are on (off flags are left at their
        defaults, so the same compiled kernels serve every effect set that leaves them off)."""
        opts = {}
        if self.antialiased:
            opts["antialiased"] = True
        if self.depth is not None:
            opts["render_depth"] = self.depth
        return opts

    def background_tensor(self, device="cpu"):
        """(3,) float32 background on ``device``, or None."""
        return None if self.background is None else torch.tensor(self.background, dtype=torch.float32, device=device)

    def head_kwargs(self) -> dict:
        """Keyword arguments of ``ScaffoldHeads`` (after feat_dim, n_offsets)."""
        return {"use_feat_bank": self.feature_bank, "appearance_dim": self.appearance_dim,
                "num_cameras": self.num_cameras if self.appearance_dim else 0,
                "add_opacity_dist": self.opacity_dist, "add_cov_dist": self.cov_dist,
                "add_color_dist": self.color_dist}

    def config_fields(self) -> dict:
        """The ``TrainConfig`` fields these effects set."""
        kw = self.head_kwargs()
        kw.pop("num_cameras")
        return kw

    def private_head_kwargs(self, bits: int = 0) -> dict:
        """Keyword arguments of ``PrivateHeads``: the decoder only for an object/image/scene branch,
        the bit head only for the bits branch."""
        return {"hidden": bool(self.hidden - {"bits"}), "bits": bits if "bits" in self.hidden else 0}

    def describe(self) -> str:
        """Stable short name: the effects that are on, joined with '+' ("base" when none)."""
        parts = []
        if self.antialiased:
            parts.append("aa")
        if self.depth:
            parts.append(f"depth-{self.depth}")
        if self.background is not None:
            parts.append("bg")
        if self.feature_bank:
            parts.append("featbank")
        if self.appearance_dim:
            parts.append(f"appearance{self.appearance_dim}")
        parts += [f"{name}-dist" for name in ("opacity", "cov", "color") if getattr(self, f"{name}_dist")]
        parts += [f"hidden-{b}" for b in sorted(self.hidden)]
        return "+".join(parts) or "base"


def infer_scene_effects(scene, payload=None, config=None) -> Effects:
    """What a ``SceneData`` asks for: a known background (NeRF-synthetic objects on white, the
    synthetic scenes) becomes the background effect; the payload (``PayloadSpec``) or the scene's
    hidden views give the hidden branches; ``config`` (``TrainConfig``) gives the head inputs."""
    hidden = set()
    kind = payload.kind if payload is not None else scene.hidden_kind
    if kind is not None:
        hidden.add(kind)
    if payload is not None and payload.bits > 0:
        hidden.add("bits")
    heads = {}
    if config is not None:
        heads = {"feature_bank": config.use_feat_bank, "appearance_dim": config.appearance_dim,
                 "num_cameras": len(scene.train) if config.appearance_dim else 0,
                 "opacity_dist": config.add_opacity_dist, "cov_dist": config.add_cov_dist,
                 "color_dist": config.add_color_dist}
    bg = None if scene.background is None else tuple(np.asarray(scene.background, dtype=np.float32).tolist())
    return Effects(background=bg, hidden=frozenset(hidden), **heads)


def heads_with_neutral_effects(plain, effects: Effects):
    """``ScaffoldHeads`` built for ``effects`` that compute exactly what ``plain`` (heads with no
    input effect) computes: plain's first-layer weights in the shared input columns, zeros in the
    extra distance / appearance columns, and a feature bank whose softmax selects the full-resolution
    feature. For checking a specialised variant against the general one, and for timing effects on
    the same Gaussians (a fresh random head would keep a different number of them)."""
    from .model import ScaffoldHeads

    d = plain.feat_dim
    heads = ScaffoldHeads(d, plain.n_offsets, **effects.head_kwargs()).to(plain.opacity_mlp[0].weight.device)
    with torch.no_grad():
        for name in ("opacity_mlp", "cov_mlp", "color_mlp"):
            src, dst = getattr(plain, name), getattr(heads, name)
            dst.load_state_dict({k: v for k, v in src.state_dict().items() if k != "0.weight"}, strict=False)
            dst[0].weight.zero_()
            dst[0].weight[:, : d + 3] = src[0].weight
        if heads.feature_bank_mlp is not None:
            heads.feature_bank_mlp[2].weight.zero_()
            heads.feature_bank_mlp[2].bias.copy_(torch.tensor([-1e4, -1e4, 1e4]))  # softmax -> (0, 0, 1)
    return heads

