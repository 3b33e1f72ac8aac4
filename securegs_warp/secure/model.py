"""``SecureModel``: a Scaffold-GS model plus the private heads of its secrets, which render each
hidden payload from the same public anchors and read each hidden message from their features."""
from __future__ import annotations

import dataclasses

import torch
from torch import nn

from ..model import AnchorModel, ScaffoldHeads
from ..model.neural_gaussians import AnchorViewInputs, visible_anchor_mask
from ..rasterizer import RasterOptions
from ..render import camera_tensors, render_view
from ..scaffold_model import ScaffoldModel, decode_all
from . import captured
from .heads import PrivateHeads
from .robust import PerturbedAnchors


class SecureModel(ScaffoldModel):
    """``secrets``: one ``PrivateHeads`` per secret (the contents of one key each). A release opened
    with a key holds that key's heads only; one opened without a key holds none and renders only
    what any Scaffold-GS viewer renders; a trainer's model holds every secret's. Methods that read a
    secret take its index ``secret`` (default the first)."""

    def __init__(self, anchors: AnchorModel, heads: ScaffoldHeads, secrets: list[PrivateHeads]):
        super().__init__(anchors, heads)
        self.secrets = nn.ModuleList(secrets)
        self._captured: dict[int, captured.CapturedRows] = {}  # per secret, while its heads are the same object

    @property
    def private(self) -> PrivateHeads | None:
        """The key's heads of a model with one secret (None: opened without a key)."""
        if len(self.secrets) > 1:
            raise ValueError(f"this model holds the heads of {len(self.secrets)} secrets: pick one by index")
        return self.secrets[0] if len(self.secrets) else None

    @property
    def renders_hidden(self) -> bool:
        """Whether the key holds a hidden decoder (an object, scene or image payload)."""
        return self.private is not None and self.private.decoder is not None

    def _key(self, secret: int) -> PrivateHeads:
        if not len(self.secrets):
            raise ValueError("this release was opened without its key: nothing hidden can be read")
        return self.secrets[secret]

    def render_hidden(self, camera, options: RasterOptions | None = None, *, background: torch.Tensor | None = None,
                      camera_index: int | None = None, feature_grad: float = 1.0, scaling_grad: float = 1.0,
                      anchors=None, secret: int = 0, visible: torch.Tensor | None = None,
                      capture: bool = False, compact: bool = True) -> dict:
        """Secret ``secret``'s hidden render of a view (as ``ScaffoldModel.render``); needs its key.

        feature_grad, scaling_grad: the share of this render's gradient that reaches the public
        anchor features and scalings (training only; see ``generate_neural_gaussians``).
        anchors: what to decode instead of this model's anchors: robust training's
        ``PerturbedAnchors`` (same rows; its ``keep`` mask drops anchors from the render). None:
        the model's, with any the key's record moves back (``_key_anchors``).
        visible: [N] bool, the anchors of ``anchors`` visible from ``camera`` (``visible_anchor_mask``)
        when the caller has them already (the public render of the same view): not computed again.
        capture: decode from CUDA graphs (``CapturedRows``) where that gives the same render: a
        box-frame key decoding its serving anchors (``fixed_rows``) on CUDA, gradients enabled, and
        no anchor registered with the key's record (``_key_anchors``: their rows vary with the attack).
        compact: False renders the Gaussians that fail the opacity test at opacity 0 instead of
        leaving them out (the same image and gradients, without a host synchronisation; the
        Gaussians' per-row statistics then count them, see ``generate_neural_gaussians``).
        """
        private = self._key(secret)
        if private.decoder is None:
            raise ValueError("this payload hides no image: there is no hidden view to render")
        source = private.hidden_offsets if private.offset_mlp is not None else self._explicit_offsets
        rows = None
        anchors = self._key_anchors(private) if anchors is None else anchors
        if capture and self.fixed_rows(secret) and captured.replayable(self.anchors.xyz) \
                and torch.is_grad_enabled() and getattr(anchors, "registered", None) is None:
            if secret not in self._captured or self._captured[secret].private is not private:
                self._captured[secret] = captured.CapturedRows(private)
            rows = self._captured[secret]
        mask, index, keep = self._decoding_rows(private, anchors, camera, visible)
        if private.eps2d is not None:
            options = dataclasses.replace(options or RasterOptions(), eps2d=private.eps2d)
        return render_view(anchors, private.decoder, camera, background, options, camera_index=camera_index,
                           offset_source=source, anchor_source=private.anchor_source, feature_grad=feature_grad,
                           scaling_grad=scaling_grad, anchor_mask=mask, anchor_index=index, rows=rows,
                           compact=compact, keep=keep)

    def fixed_rows(self, secret: int = 0) -> bool:
        """Whether secret ``secret``'s hidden renders decode the same number of rows at every view
        until the key's serving radius is refit, robust training's perturbed anchors included: a
        box-frame key's serving anchors (with perturbed positions, as many of them as lie within the
        radius unperturbed; see ``_decoding_rows``)."""
        return self._key(secret).serves_by_radius

    def _decoding_rows(self, private: PrivateHeads, anchors, camera, visible: torch.Tensor | None = None) -> tuple:
        """([N] bool or None, [Nv] long or None, [N] bool or None): the anchors whose hidden
        Gaussians ``private`` decodes for ``camera`` (the box frame's serving anchors, else the
        visible ones; None: render_view's visibility test), their indices where the key keeps them
        (else None), and the anchors among them whose Gaussians may render (robust training's
        ``PerturbedAnchors.keep``; None: all). The box frame keeps its serving rows and drops by
        ``keep`` (a fixed row count); the anchor frame leaves dropped anchors out of the mask.

        Perturbed positions (robust training's noise or quantisation) move anchors across the
        serving radius. They are served by rank instead: the anchors nearest the box as they now
        lie, as many as the radius serves unperturbed. That is the set ``fix_serving`` defines (the
        ``serving`` nearest), an attack's flips at the radius included, and its row count stays
        fixed, so the captured decoding and rasterize still replay.

        ``PerturbedAnchors`` of a key's S serving rows only (``serving_rows``) decode every row:
        ([S] True, arange(S), their ``keep``). ``PerturbedAnchors`` registered with the key's record
        (``_key_anchors``) decode their ``registered`` rows."""
        keep = getattr(anchors, "keep", None)
        registered = getattr(anchors, "registered", None)
        if registered is not None:  # registered with the key's record: its paired anchors serve
            mask = torch.zeros(anchors.num_anchors, dtype=torch.bool, device=registered.device)
            return mask.index_fill_(0, registered, True), registered, keep
        if getattr(anchors, "serving_rows", False):
            n, device = anchors.num_anchors, anchors.xyz.device
            return torch.ones(n, dtype=torch.bool, device=device), torch.arange(n, device=device), keep
        serving = private.serving_mask(self.anchors.xyz)
        if serving is not None:
            index = private.serving_index(self.anchors.xyz)
            if anchors.xyz is not self.anchors.xyz:
                index = private.nearest_serving(anchors.xyz, len(index))
                serving = torch.zeros_like(serving).index_fill_(0, index, True)
            return serving, index, keep
        if keep is None:
            return visible, None, None
        mask = visible
        if mask is None:
            viewmat, K = camera_tensors(camera, anchors.xyz.device)
            mask = visible_anchor_mask(anchors, viewmat, K, camera.width, camera.height)
        return mask & keep, None, None

    @torch.no_grad()
    def hidden_gaussians(self, camera, secret: int = 0) -> dict:
        """Every anchor decoded by secret ``secret``'s key into hidden Gaussians with ``camera``'s
        view directions (no culling; in the box frame, the serving anchors'): the whole hidden
        payload, for export (see ``ScaffoldModel.gaussians``)."""
        private = self._key(secret)
        if private.decoder is None:
            raise ValueError("this payload hides no image: there are no hidden Gaussians")
        source = private.hidden_offsets if private.offset_mlp is not None else self._explicit_offsets
        anchors = self._key_anchors(private)
        return decode_all(anchors, private.decoder, camera, offset_source=source,
                          anchor_source=private.anchor_source,
                          anchor_mask=self._decoding_rows(private, anchors, camera)[0])

    def _key_anchors(self, private: PrivateHeads):
        """What ``private`` decodes of this model's anchors: the anchors themselves, or, where the key's
        record finds them attacked (``PrivateHeads.register``: anchors shifted off their entries, or
        one it never served moved inside its radius), a ``PerturbedAnchors`` view with the registered
        positions whose ``registered`` rows alone serve."""
        xyz, rows = private.register(self.anchors.xyz)
        if rows is None:
            return self.anchors
        a = self.anchors
        return PerturbedAnchors(xyz, a.feat, a.offsets, a.scaling, a.rotation, a.opacity, registered=rows)

    def _explicit_offsets(self, inputs: AnchorViewInputs) -> torch.Tensor:
        """w/o HDGER: stored per-anchor hidden offsets [Nv, k, 3], scaled like the public ones."""
        return self.anchors.hidden_offsets[inputs.anchor_index] * inputs.scaling[:, None, :3]

    @torch.no_grad()
    def decode_bits(self, anchors: AnchorModel | None = None, secret: int = 0) -> torch.Tensor:
        """Secret ``secret``'s hidden message [L] (0/1 int64) read from the features of ``anchors``
        (default: this model's own); needs a key with a bit payload."""
        private = self._key(secret)
        if private.bits is None:
            raise ValueError("this key hides no bits")
        anchors = self.anchors if anchors is None else anchors
        return private.decode_bits(anchors.feat, anchors.xyz)
