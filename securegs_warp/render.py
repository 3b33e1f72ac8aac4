"""Render one view of anchors with a set of heads: decode the visible anchors, rasterize."""
from __future__ import annotations

import weakref

import numpy as np
import torch

from .data import Camera
from .model import generate_neural_gaussians, visible_anchor_mask
from .model.neural_gaussians import camera_center_from_viewmat
from .rasterizer import RasterOptions, rasterize


# Each camera's matrices on each device, with the values they were made from: training renders the
# same views again and again (a SecureGS step twice), and a fresh copy is a host-to-device transfer
# per matrix. An entry goes with its camera.
_DEVICE_CAMERAS: dict = {}


def camera_tensors(cam: Camera, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat [4, 4], K [3, 3]) float32 tensors of a camera on ``device`` (kept per camera and
    device while the camera's matrices keep their values; read them, do not write them). A camera
    with ``device_tensors`` set gives those instead: its owner's fixed tensors, which it writes
    before each replay of a CUDA graph that renders it (secure.hidden_graph)."""
    fixed = getattr(cam, "device_tensors", None)
    if fixed is not None:
        return fixed
    key = (id(cam), torch.device(device))
    kept = _DEVICE_CAMERAS.get(key)
    if (kept is not None and kept[0]() is cam and np.array_equal(kept[1], cam.viewmat)
            and np.array_equal(kept[2], cam.K)):
        return kept[3]
    tensors = (torch.as_tensor(cam.viewmat, dtype=torch.float32, device=device),
               torch.as_tensor(cam.K, dtype=torch.float32, device=device))
    _DEVICE_CAMERAS[key] = (weakref.ref(cam, lambda _: _DEVICE_CAMERAS.pop(key, None)),
                            np.array(cam.viewmat), np.array(cam.K), tensors)
    return tensors


def render_view(anchors, heads, cam: Camera, background: torch.Tensor | None, options: RasterOptions | None = None,
                *, camera_index: int | None = None, offset_source=None, anchor_source=None, feature_grad: float = 1.0,
                scaling_grad: float = 1.0, anchor_mask: torch.Tensor | None = None, anchor_index=None, rows=None,
                compact: bool = True, keep: torch.Tensor | None = None) -> dict:
    """Decode ``anchors`` (an ``AnchorModel``) visible from ``cam`` with ``heads`` and rasterize them.

    background: [3] colour behind the Gaussians (None: black). options: the rasterizer's options
    (default ``RasterOptions()``). camera_index: the camera's row of an appearance embedding (views
    without one of their own, held-out ones, use the first camera's). offset_source: where the
    Gaussians sit (default: the stored public offsets; SecureGS's hidden branch passes its private
    offset predictor). anchor_source: what the heads decode in place of the anchors' features and
    log scalings (a key's private latent and codes). feature_grad, scaling_grad: see ``generate_neural_gaussians``. anchor_mask:
    [N] bool, the anchors to decode (default: those whose own footprint reaches the image; a decoder
    that places Gaussians far from their anchor names its own, and robust training drops some).
    anchor_index: [Nv] long, the indices of ``anchor_mask``'s True entries, when the caller keeps
    them. rows: a ``RowDecoder`` in place of ``heads`` and ``offset_source``. compact: False keeps
    the rows that fail the opacity test, at opacity 0. keep: [N] bool, the anchors whose Gaussians
    may pass that test. (The last four: see ``generate_neural_gaussians``.)

    Returns dict: ``image`` [H, W, 3], ``alpha`` [H, W, 1], ``info`` (rasterize info),
    ``gaussians`` (generate_neural_gaussians output).
    """
    device = anchors.xyz.device
    viewmat, K = camera_tensors(cam, device)
    visible = visible_anchor_mask(anchors, viewmat, K, cam.width, cam.height) if anchor_mask is None else anchor_mask
    appearance = (camera_index or 0) if heads.appearance_dim else None
    extra = {"offset_source": offset_source} if offset_source is not None else {}
    g = generate_neural_gaussians(anchors, heads, camera_center_from_viewmat(viewmat), visible,
                                  camera_index=appearance, feature_grad=feature_grad,
                                  scaling_grad=scaling_grad, rows=rows, anchor_index=anchor_index, compact=compact,
                                  keep=keep, anchor_source=anchor_source, **extra)
    image, alpha, info = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], viewmat, K,
                                   cam.width, cam.height, background=background, options=options)
    return {"image": image, "alpha": alpha, "info": info, "gaussians": g}
