"""3DGS + StegaNeRF: a plain 3DGS scene fine-tuned so that its renders carry a hidden image, which a
U-Net decoder recovers from the render of any view (Li et al., "StegaNeRF", CVPR 2023, moved from
a Plenoxels grid to explicit Gaussians; the authors' code is chenxinli001/StegaNeRF).

The release is the fine-tuned scene as a standard 3DGS PLY; the key is the decoder (with the
classifier that guides it). StegaNeRF's fine-tuning, per step on one training view:

- render the view with the scene being tuned (I) and with the scene as it was (I₀, fixed);
- a classifier C tells renders that carry the image from the original ones (BCE, targets 1 / 0);
- the decoder D sees each render with C's belief (detached) and must give the hidden image M from
  I and black from I₀ (both MSE): so D does not paint M onto any picture it is shown;
- the scene is held to I₀ (or the ground truth, ``rgb_target``) by an MSE;
- before Adam steps the scene, the gradient of each SH coefficient is scaled down where that
  coefficient carries much of the scene's appearance (adaptive gradient masking).

``StegaNeRFConfig`` (config.py) holds every option, with the paper's choices and ours marked.
"""
from __future__ import annotations

import copy
import math
import os

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .. import evaluation
from ..config import StegaNeRFConfig
from ..gaussians import GaussianModel
from ..keys import write_private
from ..rasterizer import RasterOptions

COLOR_PARAMS = ("features_dc", "features_rest")


def _conv_block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.ReLU(inplace=True))


class StegaDecoder(nn.Module):
    """A U-Net: a render [B, 3, H, W] and the classifier's belief [B] (as a constant fourth input
    channel: StegaNeRF's classifier-guided recovery) -> an image [B, 3, H, W] in [0, 1].

    The render is first resized to ``size``² and the U-Net works there (``levels`` resolutions,
    ``width``·2^l channels at level l), its output resized back to H, W: as the authors' decoder,
    which reads a 128² copy of the render. A fixed working size with a bottleneck that sees the
    whole picture is what lets the decoder draw the hidden image at the right place in every view
    (where the hidden image is, is known to the network only through its receptive field reaching
    the borders); at the view's own size the receptive field covers a patch, and the decoder can
    learn no more than the hidden image's mean colour. ``size`` 0 works at the view's size.
    ``antialias``: a larger render is shrunk by averaging the pixels under each output pixel
    instead of sampling four of them."""

    def __init__(self, width: int = 16, levels: int = 3, size: int = 0, antialias: bool = False):
        super().__init__()
        self.size, self.antialias = size, antialias
        widths = [width * 2 ** level for level in range(levels)]
        self.encoders = nn.ModuleList(_conv_block(c_in, c_out) for c_in, c_out in zip([4] + widths[:-1], widths))
        self.decoders = nn.ModuleList(_conv_block(widths[level + 1] + widths[level], widths[level])
                                      for level in reversed(range(levels - 1)))
        self.out = nn.Conv2d(width, 3, 1)

    def working_copy(self, image: torch.Tensor) -> torch.Tensor:
        """The render [B, 3, H, W] at the size the U-Net works at ([B, 3, size, size]; itself with size 0)."""
        if not self.size:
            return image
        return F.interpolate(image, size=(self.size, self.size), mode="bilinear", align_corners=False,
                             antialias=self.antialias)

    def forward(self, image: torch.Tensor, belief: torch.Tensor, working_size: bool = False) -> torch.Tensor:
        """working_size: return the U-Net's output as it made it, [B, 3, size, size] (the authors'
        scoring size), instead of resized to the render's H, W."""
        b, _, h, w = image.shape
        image = self.working_copy(image)
        x = torch.cat([image, belief.view(b, 1, 1, 1).expand(b, 1, *image.shape[-2:])], dim=1)
        skips = []
        for level, encoder in enumerate(self.encoders):
            x = encoder(x if level == 0 else F.avg_pool2d(x, 2, ceil_mode=True))
            skips.append(x)
        for decoder, skip in zip(self.decoders, reversed(skips[:-1])):
            x = decoder(torch.cat([F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False),
                                   skip], 1))
        x = torch.sigmoid(self.out(x))
        if working_size or x.shape[-2:] == (h, w):
            return x
        return F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)


class StegaClassifier(nn.Module):
    """Whether a render [B, 3, H, W] carries the hidden image: [B] probabilities."""

    def __init__(self, width: int = 16):
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, width, 3, stride=2, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(2 * width, 4 * width, 3, stride=2, padding=1), nn.ReLU(inplace=True))
        self.head = nn.Linear(4 * width, 1)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.head(self.features(image).mean(dim=(2, 3)))[:, 0])


def sh_gradient_weights(model: GaussianModel, power: float) -> torch.Tensor:
    """[(d + 1)²] weights of the SH basis functions' gradients: (e_min / e_i)^power, e_i the mean
    |coefficient| of basis function i over Gaussians and channels (StegaNeRF's adaptive gradient
    masking: the more of the scene's energy a coefficient holds, the less it moves)."""
    coeffs = torch.cat([model.features_dc[:, None], model.features_rest], dim=1).detach()
    energy = coeffs.abs().mean(dim=(0, 2)).clamp_min(1e-12)
    return (energy.min() / energy) ** power


def _chw(image: torch.Tensor) -> torch.Tensor:
    return image.permute(2, 0, 1)[None]


class StegaNeRF:
    """Fine-tunes a copy of a trained ``GaussianModel`` to carry ``hidden`` [H, W, 3] (the views'
    size) in its renders; ``decoder`` and ``classifier`` form the key.

    scene: the ``SceneData`` the model was trained on (its training views are fine-tuned on, its
    held-out views evaluated). raster, background: as the scene was trained with.
    """

    def __init__(self, model: GaussianModel, scene, hidden: torch.Tensor, config: StegaNeRFConfig,
                 raster: RasterOptions | None = None, background: torch.Tensor | None = None, seed: int = 0):
        self.config, self.scene, self.raster, self.background = config, scene, raster, background
        self.device = model.device
        cam = scene.train[0]
        if tuple(hidden.shape) != (cam.height, cam.width, 3):
            raise ValueError(f"hidden image must be [{cam.height}, {cam.width}, 3] (the views' size), "
                             f"got {list(hidden.shape)}")
        self.hidden = hidden.to(self.device)
        self.original = model
        self.model = copy.deepcopy(model)
        tuned = {"color": COLOR_PARAMS, "dc": ("features_dc",), "all": None}[config.tune]
        for name, p in self.model.named_parameters():
            p.requires_grad_(tuned is None or name in tuned)
        torch.manual_seed(seed)  # decoder and classifier initialisation
        self.decoder = StegaDecoder(config.decoder_width, config.decoder_levels, config.decoder_size,
                                    config.decoder_antialias).to(self.device)
        self.classifier = StegaClassifier(config.decoder_width).to(self.device)
        lr = {name: config.color_lr for name in COLOR_PARAMS}
        lr.update({"means": 0.0, "log_scales": 0.005, "quats": 0.001, "opacity_logits": 0.05})  # 3DGS's, tune=all
        self.optimizer = torch.optim.Adam([{"params": [p], "lr": lr[name], "name": name}
                                           for name, p in self.model.named_parameters() if p.requires_grad], eps=1e-15)
        self.decoder_optimizer = torch.optim.Adam(
            [{"params": list(self.decoder.parameters()), "lr": config.decoder_lr, "name": "decoder"},
             {"params": list(self.classifier.parameters()), "lr": config.classifier_lr, "name": "classifier"}])
        self.sh_weights = (sh_gradient_weights(self.model, config.masking_power)
                           if config.gradient_masking and self.model.sh_degree is not None else None)
        self.generator = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            self._initial = [self.original.render(c, raster, background=background)["image"] for c in scene.train]
        self._targets = [torch.as_tensor(c.image, device=self.device) for c in scene.train]
        self.step_count = 0

    def render(self, cam) -> dict:
        """The public render of the fine-tuned scene."""
        return self.model.render(cam, self.raster, background=self.background)

    @torch.no_grad()
    def reveal(self, image: torch.Tensor, working_size: bool = False) -> torch.Tensor:
        """The decoder's reading [H, W, 3] of a render [H, W, 3], guided by the classifier
        (working_size: [S, S, 3] at the U-Net's own size, ``decoder_size``)."""
        x = _chw(image)
        return self.decoder(x, self.classifier(x), working_size)[0].permute(1, 2, 0)

    def hidden_at_working_size(self) -> torch.Tensor:
        """The hidden image at the decoder's working size (``shrink``; itself with size 0): what
        ``reveal(..., working_size=True)`` is scored against."""
        return shrink(self.hidden, self.decoder.size) if self.decoder.size else self.hidden

    def render_hidden(self, cam) -> dict:
        """The hidden image as the key holder recovers it from the public render of ``cam``."""
        return {"image": self.reveal(self.render(cam)["image"])}

    def step(self) -> dict:
        """One fine-tuning step on a random training view; returns the loss terms."""
        c = self.config
        index = int(torch.randint(len(self.scene.train), (1,), generator=self.generator))
        image = self.render(self.scene.train[index])["image"]
        initial = self._initial[index]
        target = initial if c.rgb_target == "init" else self._targets[index]
        batch = torch.cat([_chw(image), _chw(initial)])
        belief = self.classifier(batch)
        decoded = self.decoder(batch, belief.detach())
        terms = {
            "rgb": F.mse_loss(image, target),
            "hidden": F.mse_loss(decoded[0], _chw(self.hidden)[0]),
            "clean": decoded[1].square().mean(),
            "classifier": F.binary_cross_entropy(belief, torch.tensor([1.0, 0.0], device=self.device)),
        }
        loss = (c.rgb_weight * terms["rgb"] + c.hidden_weight * terms["hidden"] + c.clean_weight * terms["clean"]
                + c.classifier_weight * terms["classifier"])
        self.optimizer.zero_grad(set_to_none=True)
        self.decoder_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.sh_weights is not None:
            self.model.features_dc.grad *= self.sh_weights[0]
            if self.model.features_rest.grad is not None:
                self.model.features_rest.grad *= self.sh_weights[1:, None]
        # The authors decay both networks' rates exponentially by 10x over the run.
        decay = 0.1 ** (self.step_count / c.iterations)
        for group in self.decoder_optimizer.param_groups:
            group["lr"] = decay * (c.decoder_lr if group["name"] == "decoder" else c.classifier_lr)
        self.optimizer.step()
        self.decoder_optimizer.step()
        self.step_count += 1
        return {"loss": loss.item(), **{k: v.item() for k, v in terms.items()}}

    def train(self, on_step=None) -> None:
        """Run the configured fine-tuning steps; ``on_step(step, stats)`` sees each."""
        while self.step_count < self.config.iterations:
            stats = self.step()
            if on_step is not None:
                on_step(self.step_count, stats)

    @torch.no_grad()
    def evaluate(self, timing_repeats: int = 3) -> dict:
        """On the held-out views: the cover (public render vs the photographs), the hidden image
        (decoded from each view's render vs M), the same at the decoder's working size
        (``*_working_size``: its output before resizing against M averaged down to that size, as the
        authors score at 128²), the most a decoder of that size can score at the view's size
        (``psnr_hidden_ceiling``: ``working_size_ceiling``), what the decoder reads from
        the original scene's renders (``psnr_hidden_from_original``: a decoder that paints M onto
        anything would score high there), and the FPS of the public render and of render + decoder."""
        cams = self.scene.evaluation_views
        cover = evaluation.evaluate_views(self.render, cams, self.device, timing_repeats=timing_repeats)
        hidden = evaluation.image_metrics([(self.render_hidden(c)["image"], self.hidden) for c in cams], self.device,
                                          with_lpips=False)
        original = evaluation.image_metrics(
            [(self.reveal(self.original.render(c, self.raster, background=self.background)["image"]), self.hidden)
             for c in cams], self.device, with_lpips=False)
        small = self.hidden_at_working_size()
        working = evaluation.image_metrics(
            [(self.reveal(self.render(c)["image"], working_size=True), small) for c in cams], self.device,
            with_lpips=False)
        ceiling = working_size_ceiling(self.hidden, self.decoder.size) if self.decoder.size else None
        return {"psnr_public": cover["psnr"], "ssim_public": cover["ssim"], "fps_public": cover["fps"],
                "psnr_hidden": hidden["psnr"], "ssim_hidden": hidden["ssim"],
                "psnr_hidden_working_size": working["psnr"], "ssim_hidden_working_size": working["ssim"],
                "psnr_hidden_ceiling": ceiling,
                "psnr_hidden_from_original": original["psnr"],
                "fps_hidden": evaluation.render_fps(self.render_hidden, cams, self.device, timing_repeats)}

    # -- release and key ------------------------------------------------------------------------

    def key_tensors(self) -> dict[str, torch.Tensor]:
        return {**{f"decoder.{k}": v for k, v in self.decoder.state_dict().items()},
                **{f"classifier.{k}": v for k, v in self.classifier.state_dict().items()}}

    def key_shape(self) -> dict[str, str]:
        """The decoder's shape as the key records it: what a reader must build to load the weights."""
        c = self.config
        return {"decoder_width": str(c.decoder_width), "decoder_levels": str(c.decoder_levels),
                "decoder_size": str(c.decoder_size), "decoder_antialias": str(c.decoder_antialias)}

    def save_key(self, path: str | os.PathLike) -> None:
        """The decoder and classifier as a safetensors file (tensors only: loading runs no code),
        readable by its owner only, like every key of the project."""
        from safetensors.torch import save

        data = save({k: v.detach().cpu().contiguous() for k, v in self.key_tensors().items()},
                    metadata={"method": "3dgs+steganerf", **self.key_shape()})
        write_private(path, data)

    def load_key(self, path: str | os.PathLike) -> None:
        """Read a key written by :meth:`save_key` into the decoder and classifier; ValueError naming
        the file when it is not one, or of another decoder shape."""
        from safetensors import SafetensorError, safe_open

        try:
            with safe_open(str(path), framework="pt", device="cpu") as f:
                metadata = f.metadata() or {}
                tensors = {k: f.get_tensor(k) for k in f.keys()}
        except (OSError, SafetensorError) as e:
            raise ValueError(f"{path}: not a StegaNeRF key ({e})") from None
        shape = self.key_shape()
        metadata = {"decoder_antialias": "False", **metadata}  # keys written before the option sampled
        differ = [f"{k} {metadata.get(k)} (this decoder: {v})" for k, v in shape.items() if metadata.get(k) != v]
        if metadata.get("method") != "3dgs+steganerf" or differ:
            raise ValueError(f"{path}: not a key for this decoder ({'; '.join(differ) or 'another method'})")
        for prefix, module in (("decoder.", self.decoder), ("classifier.", self.classifier)):
            part = {k[len(prefix):]: v.to(self.device) for k, v in tensors.items() if k.startswith(prefix)}
            try:
                module.load_state_dict(part)
            except RuntimeError as e:
                raise ValueError(f"{path}: not a key for this decoder ({str(e).splitlines()[0]})") from None


@torch.no_grad()
def shrink(image: torch.Tensor, size: int) -> torch.Tensor:
    """An image [H, W, 3] at [size, size, 3]: each output pixel the mean of the input pixels under it
    where it shrinks (``cv2.INTER_AREA``, as the authors resize their watermark), bilinear where it
    grows."""
    mode = "area" if min(image.shape[:2]) >= size else "bilinear"
    extra = {} if mode == "area" else {"align_corners": False}
    return F.interpolate(_chw(image), size=(size, size), mode=mode, **extra)[0].permute(1, 2, 0)


def _bilinear_matrix(length: int, size: int) -> torch.Tensor:
    """[length, size]: the 1-D map of ``StegaDecoder``'s bilinear resize from size to length samples."""
    eye = torch.eye(size, dtype=torch.float64)[None, None]
    return F.interpolate(eye, size=(length, size), mode="bilinear", align_corners=False)[0, 0]


@torch.no_grad()
def working_size_ceiling(hidden: torch.Tensor, size: int) -> float:
    """The most PSNR (dB) at the view's size that any drawing at size² scores against the hidden
    image [H, W, 3], once ``StegaDecoder`` resizes it to H, W. The resize is linear and separable
    (A X Bᵀ per channel), so the least-squares drawing X = A⁺ M (B⁺)ᵀ has the least error of all,
    those in [0, 1] included: no decoder of that size scores more."""
    h, w = hidden.shape[:2]
    a, b = _bilinear_matrix(h, size), _bilinear_matrix(w, size)
    target = hidden.detach().double().cpu().permute(2, 0, 1)
    fit = a @ (torch.linalg.pinv(a) @ target @ torch.linalg.pinv(b).T) @ b.T
    # Not train.losses.psnr: it clamps the fit to [0, 1], which a decoder's sigmoid output never
    # needs, and so would loosen the bound.
    mse = float(((fit - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def hidden_image_for(scene, image: str = "builtin") -> np.ndarray:
    """The image to hide, at the views' size [H, W, 3]: ``builtin`` (the payload module's emblem,
    what SecureGS's ``image`` payload hides by default) or an image file."""
    from ..data.cameras import read_image, resize_image
    from ..secure.payload import builtin_emblem

    cam = scene.train[0]
    raw = builtin_emblem(cam.height, cam.width) if image == "builtin" else read_image(image)[0]
    return resize_image(raw, (cam.width, cam.height)).astype(np.float32)
