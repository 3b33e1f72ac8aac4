"""GS-Hider (Zhang et al., "GS-Hider: Hiding Messages into 3D Gaussian Splatting", NeurIPS 2024) on
this engine; the authors' code is xuanyuzhang21/GS-Hider.

Each Gaussian carries a coupled feature f ∈ R^M (M = 16) in place of 3DGS's SH colour, stored as a
logit and rendered through its sigmoid by the same rasterizer (``securegs_warp.rasterize`` with
C = M) into a feature map F [H, W, M]. Two convolutional decoders read F: the public scene decoder
gives the cover view, the private message decoder the hidden one. Per step, on one training view:

    ℓ = ℓ(D_scene(F), I) + w·ℓ(D_message(F), I_hid),  ℓ = 0.8·L1 + 0.2·(1 − SSIM), w = 0.5,

the Gaussians and both decoders trained jointly, with 3DGS's densification (``GaussianStrategy``).
A hidden 3D scene (or object) gives I_hid at every training view; a single image is hidden at one
view, whose feature map is rendered and decoded every step, the other views' message left free
(as SecureGS describes GS-Hider's image setting).

What GS-Hider publishes, and what its key is::

    OUT/public/point_cloud.ply            x y z nx ny nz opacity scale_0..2 rot_0..3 semantic_0..M-1
                                          (GS-Hider's own layout: no f_dc, so not a 3DGS viewer file)
    OUT/public/scene_decoder.safetensors  the scene decoder's weights and shape
    OUT/key.safetensors (or key.sealed)   the message decoder, a key file (``securegs_warp.keys``)
                                          bound to the release by a fingerprint of the scene decoder

The authors save their decoders with ``torch.save`` (a pickle); here both are safetensors, so
opening a release or a key never executes anything from it.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import torch
import torch.nn.functional as F
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as safetensors_bytes
from torch import nn

from .. import evaluation
from ..config import GSHiderConfig, TrainConfig
from ..data import Camera, SceneData
from ..gaussians import GaussianModel
from ..gaussians.attacks import attack_gaussians
from ..gaussians.model import PLY_FILE
from ..io.atomic import atomic_write
from ..io.gs_ply import PlyFormatError, read_vertex_ply, vertex_columns, write_vertex_ply
from ..keys import KeyFileError, container_fingerprint, load_key, save_key
from ..rasterizer import RasterOptions
from ..secure.container import PUBLIC_DIR, default_key_path, remove_stale_key
from ..secure.payload import Payload, PayloadSpec, build_payload
from ..train.gaussians import GaussianTrainer
from ..train.losses import psnr

SCENE_DECODER_FILE = "scene_decoder.safetensors"
DECODER_FORMAT = "gs-hider-decoder"
_KEY_PREFIX = "message_decoder."


class FeatureDecoder(nn.Module):
    """GS-Hider's decoder: ``layers`` 3×3 convolutions (padding 1), ReLU between them, ``channels``
    -> ``width`` -> ... -> 3, no activation on the output (as the authors'; renders are clamped to
    [0, 1] when measured). Maps a feature map [H, W, C] to an image [H, W, 3]."""

    def __init__(self, channels: int = 16, width: int = 64, layers: int = 5):
        super().__init__()
        sizes = [channels] + [width] * (layers - 1) + [3]
        self.convs = nn.ModuleList(nn.Conv2d(a, b, 3, padding=1) for a, b in zip(sizes[:-1], sizes[1:]))
        self.shape = {"channels": channels, "width": width, "layers": layers}

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if features.ndim != 3 or features.shape[-1] != self.shape["channels"]:
            raise ValueError(f"the decoder reads [H, W, {self.shape['channels']}] feature maps, "
                             f"got {list(features.shape)}")
        x = features.permute(2, 0, 1)[None]
        for conv in self.convs[:-1]:
            x = F.relu(conv(x))
        return self.convs[-1](x)[0].permute(1, 2, 0)


class GSHiderModel(GaussianModel):
    """Gaussians with a coupled feature (``features_dc`` [N, M] holds its logits; no SH) and the
    decoders that read their feature map: ``scene_decoder`` (public) and ``message_decoder``
    (private; None for a release opened without its key).

    ``render`` is the public render (the trainers' interface); ``render_public`` and
    ``render_hidden`` are the two images a viewer and a key holder see.
    """

    def __init__(self, gaussians: dict, scene_decoder: FeatureDecoder, message_decoder: FeatureDecoder | None = None,
                 feature_background: float = 0.0):
        super().__init__(**gaussians, sh_degree=None)
        for name, decoder in (("scene decoder", scene_decoder), ("message decoder", message_decoder)):
            if decoder is not None and decoder.shape["channels"] != self.channels:
                raise ValueError(f"the {name} reads {decoder.shape['channels']} feature channels but the Gaussians "
                                 f"carry {self.channels}")
        self.scene_decoder = scene_decoder
        self.message_decoder = message_decoder
        self.feature_background = float(feature_background)

    @classmethod
    def initial(cls, points, config: GSHiderConfig) -> "GSHiderModel":
        """3DGS's initialisation from a point cloud ``points`` [P, 3], features at logit 0 (0.5
        after the sigmoid, as GS-Hider starts them), and freshly initialised decoders."""
        points = torch.as_tensor(points, dtype=torch.float32)
        start = GaussianModel.from_points(points, torch.zeros(points.shape[0], config.channels), sh_degree=None)
        shape = {"channels": config.channels, "width": config.decoder_width, "layers": config.decoder_layers}
        return cls(gaussian_tensors(start), FeatureDecoder(**shape), FeatureDecoder(**shape), config.feature_background)

    def colors(self, camera_center: torch.Tensor, sh_degree: int | None = None) -> torch.Tensor:
        """[N, M] rendered features: the sigmoid of the stored logits (GS-Hider's activation)."""
        return torch.sigmoid(self.features_dc)

    def render_features(self, camera: Camera, options: RasterOptions | None = None) -> dict:
        """The coupled feature map: ``image`` [H, W, M], ``alpha``, ``info``, ``gaussians``."""
        background = torch.full((self.channels,), self.feature_background, device=self.device)
        return GaussianModel.render(self, camera, options, background=background)

    def render(self, camera: Camera, options: RasterOptions | None = None, *, background=None,
               sh_degree: int | None = None, camera_index: int | None = None) -> dict:
        """The public render: ``image`` [H, W, 3] (the scene decoder's), ``alpha``, ``info`` with
        the feature map as ``info["features"]`` [H, W, M] (the message decoder reads the same map
        in training), ``gaussians``. background, sh_degree, camera_index: the trainers' common
        interface, unused (the feature background is the model's; a feature has no SH)."""
        out = self.render_features(camera, options)
        out["info"]["features"] = out["image"]
        return {**out, "image": self.scene_decoder(out["image"])}

    @torch.no_grad()
    def render_public(self, camera: Camera, options: RasterOptions | None = None) -> torch.Tensor:
        """What anyone with the release sees from ``camera``: [H, W, 3]."""
        return self.scene_decoder(self.render_features(camera, options)["image"])

    @torch.no_grad()
    def render_hidden(self, camera: Camera, options: RasterOptions | None = None) -> torch.Tensor:
        """What the key holder sees from ``camera``: the message decoder's image [H, W, 3]."""
        if self.message_decoder is None:
            raise KeyFileError("this GS-Hider release was opened without its key: the message decoder is the key")
        return self.message_decoder(self.render_features(camera, options)["image"])

    # -- files ----------------------------------------------------------------------------------

    def save(self, folder: str | os.PathLike, passphrase: str | None = None, metadata: dict | None = None
             ) -> tuple[Path, Path]:
        """Write the release (``folder/public``) and the key (``folder/key.safetensors``, or
        ``key.sealed`` with a passphrase); returns (public folder, key path). metadata: JSON-able
        dict stored in the key beside the decoder's shape."""
        if self.message_decoder is None:
            raise KeyFileError("cannot write a key: this model was opened without its message decoder")
        folder = Path(folder)
        public = folder / PUBLIC_DIR
        public.mkdir(parents=True, exist_ok=True)
        write_feature_ply(public / PLY_FILE, self)
        write_decoder(public / SCENE_DECODER_FILE, self.scene_decoder, self.feature_background)
        key = default_key_path(folder, passphrase)
        remove_stale_key(folder, passphrase)
        tensors = {_KEY_PREFIX + name: t.detach() for name, t in self.message_decoder.state_dict().items()}
        save_key(key, tensors, {**(metadata or {}), "gs_hider": self.message_decoder.shape},
                 decoder_fingerprint(self.scene_decoder), passphrase)
        return public, key

    @classmethod
    def load(cls, release: str | os.PathLike, key: str | os.PathLike | None = None, passphrase: str | None = None,
             device="cpu") -> "GSHiderModel":
        """Open a release (the folder ``save`` wrote, or its ``public`` folder) and, with its key,
        the message decoder. A missing or damaged file raises an error naming it; a key made for
        another release raises ``KeyFileError``."""
        public = Path(release)
        if (public / PUBLIC_DIR).is_dir():
            public = public / PUBLIC_DIR
        if not public.is_dir():
            raise FileNotFoundError(f"{public}: no GS-Hider release folder there")
        scene_decoder, background = read_decoder(public / SCENE_DECODER_FILE)
        try:
            model = cls(read_feature_ply(public / PLY_FILE), scene_decoder, None, background)
        except PlyFormatError:
            raise
        except ValueError as e:  # the point cloud and the decoder disagree (channel count, shapes)
            raise ValueError(f"{public}: {e}") from None
        if key is not None:
            model.message_decoder = read_message_decoder(key, passphrase, scene_decoder)
            if model.message_decoder.shape["channels"] != model.channels:
                raise KeyFileError(f"{key}: its decoder reads {model.message_decoder.shape['channels']} feature "
                                   f"channels, the release carries {model.channels}")
        return model.to(device).eval()


def gaussian_tensors(model: GaussianModel) -> dict:
    """The per-Gaussian parameters of ``model`` as detached tensors, by ``GaussianModel`` argument name."""
    return {name: getattr(model, name).detach() for name in
            ("means", "log_scales", "quats", "opacity_logits", "features_dc", "features_rest")}


# -- the release's files --------------------------------------------------------------------------


def feature_ply_properties(channels: int) -> list[str]:
    """The vertex properties of GS-Hider's point cloud (its ``construct_list_of_attributes``)."""
    return (["x", "y", "z", "nx", "ny", "nz", "opacity"] + [f"scale_{i}" for i in range(3)]
            + [f"rot_{i}" for i in range(4)] + [f"semantic_{i}" for i in range(channels)])


def write_feature_ply(path: str | os.PathLike, model: GaussianModel) -> None:
    """Write the Gaussians of ``model`` (features as stored logits) in GS-Hider's layout, atomically."""
    with torch.no_grad():
        values = torch.cat([model.means, torch.zeros_like(model.means), model.opacity_logits[:, None], model.log_scales,
                            F.normalize(model.quats, dim=1), model.features_dc], dim=1)
    write_vertex_ply(path, feature_ply_properties(model.channels), values.cpu().numpy())


def read_feature_ply(path: str | os.PathLike) -> dict:
    """Read GS-Hider's point cloud -> ``GaussianModel`` arguments (``features_dc`` [N, M] logits)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the release's point cloud is missing")
    vertex = read_vertex_ply(path)
    present = {p.name for p in vertex.properties}
    channels = sum(1 for i in range(len(present)) if f"semantic_{i}" in present)
    if channels == 0:
        raise PlyFormatError(path, "no semantic_* properties: not a GS-Hider point cloud")
    names = [n for n in feature_ply_properties(channels) if n not in ("nx", "ny", "nz")]
    values = torch.from_numpy(vertex_columns(path, vertex, names))
    if not torch.isfinite(values).all():
        raise PlyFormatError(path, "holds non-finite values")
    means, logits, log_scales, quats, features = values.split([3, 1, 3, 4, channels], dim=1)
    return {"means": means, "log_scales": log_scales, "quats": quats, "opacity_logits": logits[:, 0],
            "features_dc": features, "features_rest": features.new_zeros(features.shape[0], 0, channels)}


def write_decoder(path: str | os.PathLike, decoder: FeatureDecoder, feature_background: float) -> None:
    """The scene decoder as safetensors, its shape and the feature background in the metadata."""
    tensors = {name: t.detach().cpu().contiguous() for name, t in decoder.state_dict().items()}
    meta = {"format": DECODER_FORMAT, "shape": json.dumps(decoder.shape), "feature_background": repr(feature_background)}
    data = safetensors_bytes(tensors, metadata=meta)
    atomic_write(path, lambda f: f.write(data))


def read_decoder(path: str | os.PathLike) -> tuple[FeatureDecoder, float]:
    """(scene decoder, feature background) from a file written by :func:`write_decoder`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the release's scene decoder is missing")
    try:
        with safe_open(os.fspath(path), framework="pt") as f:  # parses the header and raw bytes only
            meta = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable safetensors file ({e})") from None
    if meta.get("format") != DECODER_FORMAT:
        raise ValueError(f"{path}: not a GS-Hider scene decoder (format {meta.get('format')!r})")
    try:
        decoder = FeatureDecoder(**json.loads(meta["shape"]))
        decoder.load_state_dict(tensors)
        background = float(meta["feature_background"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"{path}: the decoder's weights do not match its stated shape ({str(e)[:200]})") from None
    return decoder, background


def decoder_fingerprint(decoder: FeatureDecoder) -> str:
    """The release's fingerprint: a hash of its scene decoder's weights (which the key is bound to)."""
    return container_fingerprint({k: v.detach() for k, v in decoder.state_dict().items()})


def read_message_decoder(key: str | os.PathLike, passphrase: str | None, scene_decoder: FeatureDecoder
                         ) -> FeatureDecoder:
    """The message decoder from a key file made for the release whose scene decoder is given."""
    tensors, metadata = load_key(key, passphrase, expected_fingerprint=decoder_fingerprint(scene_decoder))
    try:
        decoder = FeatureDecoder(**metadata["gs_hider"])
        decoder.load_state_dict({name[len(_KEY_PREFIX):]: t for name, t in tensors.items()})
    except (KeyError, TypeError, RuntimeError) as e:
        raise KeyFileError(f"{key}: not a GS-Hider key ({str(e)[:200]})") from None
    return decoder


# -- training ---------------------------------------------------------------------------------------


def hidden_payload(scene: SceneData, hidden: str | Payload, device) -> Payload:
    """The hidden targets: a ``Payload`` as given, or built from a payload spec ("scene", "object",
    "image[:FILE[@VIEW]]"). GS-Hider hides images, so bits are refused."""
    payload = hidden if isinstance(hidden, Payload) else build_payload(PayloadSpec.parse(hidden), scene,
                                                                       torch.device(device))
    if payload.bits is not None or not payload.has_images:
        raise ValueError(f"GS-Hider hides a 3D scene, an object's views or one image, not bits "
                         f"(payload {payload.spec.describe()!r})")
    return payload


class GSHiderTrainer(GaussianTrainer):
    """Trains a ``GSHiderModel``: the 3DGS trainer (densification, schedules) with the feature
    field in place of SH colours, both decoders in the same Adam (their own learning rate and
    PyTorch's default eps, as the authors' separate optimisers), and the message loss.

    Attributes beyond the base class: ``hider`` (``GSHiderConfig``), ``payload`` (the hidden targets).
    """

    model_state_keys = ("model", "decoders")

    def __init__(self, scene: SceneData, config: TrainConfig, hider: GSHiderConfig, hidden: str | Payload,
                 device: str | torch.device = "cpu"):
        self.hider = hider
        self.payload = hidden_payload(scene, hidden, device)
        super().__init__(scene, config, device, model=GSHiderModel.initial(scene.points, hider))

    def _make_optimizer(self) -> torch.optim.Adam:
        optimizer = super()._make_optimizer()
        for name in ("scene_decoder", "message_decoder"):
            optimizer.add_param_group({"params": list(getattr(self.model, name).parameters()),
                                       "lr": self.hider.decoder_lr, "eps": 1e-8, "name": name})
        return optimizer

    def render(self, cam: Camera, camera_index: int | None = None) -> dict:
        return self.model.render(cam, self.config.raster)

    def extra_losses(self, index: int, renders: list, branches: dict, step: int) -> dict:
        p = self.payload
        if p.views is not None:
            features, target = branches["public"][1]["features"], p.views[index]
        else:
            features, target = self.model.render_features(self.scene.train[p.image_view], self.config.raster)["image"], p.image
        hidden = self.model.message_decoder(features)
        renders.append(({"image": hidden}, target, self.hider.hidden_weight))
        return {"psnr_hidden": psnr(hidden.detach(), target)}

    def model_state(self) -> dict:
        return {**super().model_state(),
                "decoders": {name: getattr(self.model, name).state_dict() for name in ("scene_decoder", "message_decoder")}}

    def restore_model(self, state: dict) -> None:
        decoders = {name: FeatureDecoder(**getattr(self.model, name).shape) for name in ("scene_decoder", "message_decoder")}
        for name, decoder in decoders.items():
            decoder.load_state_dict(state["decoders"][name])
        self.model = GSHiderModel(state["model"], **decoders, feature_background=self.hider.feature_background).to(self.device)
        self.optimizer = self._make_optimizer()

    def config_sections(self) -> dict:
        return {**super().config_sections(), "gs_hider": self.hider}


def train_gs_hider(scene: SceneData, hidden: str | Payload, iterations: int, seed: int = 0, device="cpu",
                   config: GSHiderConfig | None = None, train: TrainConfig | None = None, on_step=None
                   ) -> GSHiderModel:
    """Train GS-Hider on ``scene`` hiding ``hidden`` (a payload spec or a ``Payload``) for
    ``iterations`` steps; returns the model in eval mode (``render_public``, ``render_hidden``,
    ``save``; ``GSHiderModel.load`` opens what ``save`` wrote). train: the 3DGS options (default
    ``TrainConfig(model="3dgs")``; its iterations and seed are replaced by the arguments).
    ``on_step(step, stats)`` sees each step's numbers."""
    train = dataclasses.replace(train or TrainConfig(model="3dgs"), iterations=iterations, seed=seed)
    torch.manual_seed(seed)  # the decoders' initial weights
    trainer = GSHiderTrainer(scene, train, config or GSHiderConfig(), hidden, device)
    while trainer.step_count < iterations:
        stats = trainer.step()
        if on_step is not None:
            on_step(trainer.step_count, stats)
    return trainer.model.eval()


@torch.no_grad()
def evaluate_gs_hider(model: GSHiderModel, scene: SceneData, payload: Payload, options: RasterOptions | None = None,
                      timing_repeats: int = 3) -> dict:
    """On the held-out views (the training views where the hidden targets are only known there):

    psnr_public, ssim_public: the cover (scene decoder against the photographs); psnr_hidden,
    ssim_hidden: the message decoder against the hidden targets (at the image's view for an image);
    psnr_hidden_public: the scene decoder's output against the same hidden targets (what the release
    alone gives of the hidden message); fps_public, fps_hidden (rasterize + decoder);
    gaussians.
    """
    cams = scene.evaluation_views
    cover = evaluation.evaluate_views(lambda c: {"image": model.render_public(c, options)}, cams, model.device,
                                      timing_repeats=timing_repeats)
    if payload.views is not None and payload.test_views is not None and scene.test:
        hidden_cams, targets = scene.test, payload.test_views
    elif payload.views is not None:
        hidden_cams, targets = scene.train, payload.views
    else:
        hidden_cams, targets = [scene.train[payload.image_view]], [payload.image]
    features = [model.render_features(c, options)["image"] for c in hidden_cams]
    hidden = evaluation.image_metrics([(model.message_decoder(f), t) for f, t in zip(features, targets)],
                                      model.device, with_lpips=False)
    leak = evaluation.image_metrics([(model.scene_decoder(f), t) for f, t in zip(features, targets)],
                                    model.device, with_lpips=False)
    return {"psnr_public": cover["psnr"], "ssim_public": cover["ssim"], "fps_public": cover["fps"],
            "psnr_hidden": hidden["psnr"], "ssim_hidden": hidden["ssim"], "psnr_hidden_public": leak["psnr"],
            "fps_hidden": evaluation.render_fps(lambda c: {"image": model.render_hidden(c, options)}, cams,
                                                model.device, timing_repeats),
            "gaussians": model.num_gaussians}


def release_bytes(public: str | os.PathLike) -> int:
    """The size of a release folder (every file in it), in bytes."""
    return int(sum(p.stat().st_size for p in Path(public).rglob("*") if p.is_file()))


def compare_row(setup) -> tuple[dict, np.ndarray]:
    """GS-Hider's row of ``baselines.comparison`` (its ``Setup``: scene, payload, budget, attacks):
    the image payload hidden at training view 0 as SecureGS hides it, the object as every view's
    hidden target; the attacks act on the explicit Gaussians (``gaussians.attacks``). Returns the
    row and the public Gaussian means [N, 3]."""
    spec = "image:builtin@0" if setup.payload == "image" else "object"
    payload = hidden_payload(setup.scene, spec, setup.device)
    t0 = time.perf_counter()
    train = dataclasses.replace(setup.train, model="3dgs")
    model = train_gs_hider(setup.scene, payload, train.iterations, seed=train.seed, device=setup.device, train=train,
                           on_step=setup.progress("GS-Hider:", train.iterations,
                                                  lambda stats: f"hidden {stats['psnr_hidden']:.2f} dB"))
    seconds = time.perf_counter() - t0
    ev = evaluate_gs_hider(model, setup.scene, payload, train.raster)
    with tempfile.TemporaryDirectory() as tmp:
        public, _ = model.save(tmp)
        release_mb = release_bytes(public) / 1e6
    after, generator = {}, torch.Generator().manual_seed(0)
    for attack in setup.parsed_attacks:
        attacked = copy.deepcopy(model)
        report = attack_gaussians(attacked, attack, generator)
        after[attack.text] = (evaluate_gs_hider(attacked, setup.scene, payload, train.raster, timing_repeats=1)
                              ["psnr_hidden"] if report["applicable"] else None)
    where = "training view 0" if setup.payload == "image" else "every held-out view"
    row = {"method": "GS-Hider", **{k: ev[k] for k in ("psnr_public", "ssim_public", "fps_public", "psnr_hidden",
                                                          "ssim_hidden", "fps_hidden")},
           "release_mb": release_mb,
           "release_format": "GS-Hider feature PLY (16 feature columns, no colour: not a standard 3DGS file) + "
                             "scene decoder; key: message decoder",
           "primitives": f"{ev['gaussians']} Gaussians", "train_seconds": seconds, "hidden_psnr_after": after,
           "note": f"hidden scored at {where}; the release alone (scene decoder) gives "
                   f"{ev['psnr_hidden_public']:.1f} dB of it"}
    return row, model.means.detach().cpu().numpy()


__all__ = ["FeatureDecoder", "GSHiderModel", "GSHiderTrainer", "evaluate_gs_hider", "hidden_payload",
           "release_bytes", "train_gs_hider", "compare_row"]
