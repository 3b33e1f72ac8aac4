"""What an adversary can do to a public release (anchors + public MLPs) without the key.

An attack is written ``NAME[:ARG[:ARG]]`` (``ATTACK_SYNTAX`` lists them) and changes a
``ScaffoldModel`` in place; attacks compose left to right (``apply_attacks``). N anchors, k offsets,
d feature channels throughout.

- ``prune-random:F`` removes round(F·N) anchors drawn at random; ``prune-opacity:F`` the round(F·N)
  with the lowest total opacity (the sum of the opacities of each anchor's decoded public Gaussians,
  averaged over the context's cameras): what a size-reducing tool removes first.
- ``noise-xyz:S``, ``noise-feat:S``, ``noise-offset:S`` add Gaussian noise to the positions, features
  or offsets: per column (a coordinate, a feature channel, one offset's coordinate), σ = S times the
  column's standard deviation over the anchors.
- ``sor:K:STD``: statistical outlier removal over the anchor positions (as Open3D's
  ``remove_statistical_outlier``): anchors whose mean distance to their K nearest anchors exceeds the
  mean of that distance plus STD standard deviations are removed.
- ``quantize:B``: every anchor attribute to B bits per value, uniform between each column's min and max.
- ``half``: a float16 round trip of every anchor attribute and of the public MLP weights.
- ``purify:F``: the GSPure idea on anchors. Each anchor's contribution to the public renders is the
  alpha-weighted pixel coverage of its Gaussians, Σ over the context's cameras, pixels and its
  Gaussians of T·α (the weight the Gaussian's colour gets in the pixel), summed exactly through the
  rasterizer's gradient with respect to the colours. Anchors are clustered by k-means (32
  clusters) on their standardised position, log contribution and total opacity; a cluster's
  suspicion is the mean over its anchors of z(−log contribution) + z(isolation), isolation being the
  mean distance to the 8 nearest anchors of at least median contribution (the visible surfaces). The
  most suspicious clusters are pruned first (anchors in a cluster by their own suspicion) until
  round(F·N) anchors are gone: what serves the hidden payload alone renders little in public and,
  where the hidden object stands in empty space, stands apart from the visible surfaces.
- ``finetune:N``: the attacker trains the release for N steps on the cover's training views with
  the public loss and heads only (Scaffold-GS's learning-rate schedules compressed to N steps, no
  densification). Needs the cover's scene.
- ``export-roundtrip``: decoding to a standard 3DGS PLY and reading it back. Not applicable to a
  Scaffold-GS release: a 3DGS PLY has no anchors, features or MLPs to read back into one (reported
  as ``not_applicable`` with that reason, the model unchanged).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from .config import TrainConfig
from .data import Camera, SceneData
from .model import generate_neural_gaussians
from .model.neural_gaussians import camera_center_from_viewmat
from .rasterizer import RasterOptions, rasterize
from .render import camera_tensors
from .scaffold_model import ScaffoldModel, decode_all

ATTACK_SYNTAX = ("prune-random:F", "prune-opacity:F", "noise-xyz:S", "noise-feat:S", "noise-offset:S", "sor:K:STD",
                 "quantize:B", "half", "purify:F", "finetune:N", "export-roundtrip")
ATTACK_NAMES = tuple(syntax.split(":")[0] for syntax in ATTACK_SYNTAX)
EXPORT_NOT_APPLICABLE = ("a standard 3DGS PLY holds decoded Gaussians, not anchors, features or MLPs: a Scaffold-GS "
                         "release cannot be read back from one")
FINETUNE_NEEDS_SCENE = ("finetune needs the cover's training views: give --scene (and the scene options it was "
                        "trained with)")
PURIFY_CLUSTERS = 32
ISOLATION_NEIGHBOURS = 8


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 <= value < 1.0:
        raise ValueError
    return value


def _strength(text: str) -> float:
    value = float(text)
    if not (value >= 0.0 and math.isfinite(value)):
        raise ValueError
    return value


def _count(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise ValueError
    return int(text)


def _bits(text: str) -> int:
    value = _count(text)
    if value > 16:
        raise ValueError
    return value


# Argument parsers per attack name, in the order of ATTACK_SYNTAX.
_ARGUMENTS = {"prune-random": (_fraction,), "prune-opacity": (_fraction,), "noise-xyz": (_strength,),
              "noise-feat": (_strength,), "noise-offset": (_strength,), "sor": (_count, _strength),
              "quantize": (_bits,), "half": (), "purify": (_fraction,), "finetune": (_count,),
              "export-roundtrip": ()}
_MEANING = {_fraction: "a fraction in [0, 1)", _strength: "a finite number >= 0", _count: "an integer >= 1",
            _bits: "bits per value, 1 to 16"}


@dataclasses.dataclass(frozen=True)
class Attack:
    """One parsed attack: ``name`` and its arguments ``args`` (floats and ints, as ATTACK_SYNTAX)."""

    name: str
    args: tuple = ()

    @classmethod
    def parse(cls, text: str, names=None) -> "Attack":
        """``NAME[:ARG...]`` -> Attack; anything else raises a one-line ValueError listing the valid
        specs. names: the attack names accepted here (default: all), which the message lists."""
        valid = [s for s, n in zip(ATTACK_SYNTAX, ATTACK_NAMES) if names is None or n in names]
        name, *raw = text.strip().split(":")
        if name not in _ARGUMENTS or (names is not None and name not in names):
            raise ValueError(f"unknown attack {text!r}; valid: {', '.join(valid)}")
        parsers = _ARGUMENTS[name]
        syntax = ATTACK_SYNTAX[ATTACK_NAMES.index(name)]
        if len(raw) != len(parsers):
            raise ValueError(f"attack {text!r} must be written {syntax}; valid: {', '.join(valid)}")
        args = []
        for parse, value in zip(parsers, raw):
            try:
                args.append(parse(value))
            except ValueError:
                raise ValueError(f"attack {text!r}: {value!r} is not {_MEANING[parse]} ({syntax}); valid: "
                                 f"{', '.join(valid)}") from None
        return cls(name, tuple(args))

    @property
    def text(self) -> str:
        """The spec as ATTACK_SYNTAX writes it, each number in its shortest form that reads back as
        the same value (a config compares recipes by this text, and a run trains on what it reads)."""
        return ":".join([self.name, *(f"{a:g}" if float(f"{a:g}") == a else repr(a) for a in self.args)])

    @property
    def changes_heads(self) -> bool:
        """Whether it changes the public MLP weights (and so the release's fingerprint the key is bound to)."""
        return self.name in ("half", "finetune")

    @property
    def needs_scene(self) -> bool:
        return self.name == "finetune"

    @property
    def draws_randomly(self) -> bool:
        """Whether it reads ``AttackContext.generator`` (another seed attacks other anchors, adds
        other noise or clusters from another start); the rest give the same release for any seed
        (``finetune`` draws its views from ``AttackContext.train``'s seed instead)."""
        return self.name in ("prune-random", "noise-xyz", "noise-feat", "noise-offset", "purify")


def parse_attacks(specs) -> list[Attack]:
    """Parse every spec (strings) before anything runs; an empty list is refused."""
    if not specs:
        raise ValueError(f"no attack given; valid: {', '.join(ATTACK_SYNTAX)}")
    return [Attack.parse(s) for s in specs]


@dataclasses.dataclass
class AttackContext:
    """What attacks may use besides the model.

    cameras: views the attacker renders from (prune-opacity, purify): the key's cameras.
    raster: rasterizer options. background: [3] public background or None.
    generator: CPU random source of every random draw (the same seed gives the same attack).
    scene: the cover's data (finetune), or None. train: training options finetune starts from.
    """

    cameras: list[Camera]
    raster: RasterOptions = dataclasses.field(default_factory=RasterOptions)
    background: torch.Tensor | None = None
    generator: torch.Generator = dataclasses.field(default_factory=lambda: torch.Generator().manual_seed(0))
    scene: SceneData | None = None
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)


# ---------------------------------------------------------------------------------------------
# Primitives (robust training applies the same ones to the hidden branch's inputs)
# ---------------------------------------------------------------------------------------------


def random_prune_mask(n: int, fraction, generator: torch.Generator, device="cpu") -> torch.Tensor:
    """[n] bool on ``device`` with exactly round(fraction·n) True entries at random places (drawn
    on ``generator``'s device). fraction: a number, or a 0-d tensor on ``generator``'s device: the
    count then never goes to the host (each entry's rank in a random order is compared with it), so
    a CUDA graph can replay the draw (secure.hidden_graph)."""
    count = torch.round(fraction * n) if torch.is_tensor(fraction) else round(fraction * n)
    ranks = torch.rand(n, generator=generator, device=generator.device).argsort().argsort()
    return (ranks < count).to(device)


def lowest_mask(score: torch.Tensor, fraction: float) -> torch.Tensor:
    """[N] bool marking the round(fraction·N) lowest entries of ``score`` [N]."""
    mask = torch.zeros(score.shape[0], dtype=torch.bool, device=score.device)
    mask[torch.argsort(score, stable=True)[: round(fraction * score.shape[0])]] = True
    return mask


def column_noise(values: torch.Tensor, strength: float, generator: torch.Generator,
                 std: torch.Tensor | None = None) -> torch.Tensor:
    """Gaussian noise shaped like ``values`` [N, ...]: per column (each index past the first), σ is
    ``strength`` times that column's standard deviation over the N rows (0 for a single row), or
    times ``std`` [1, ...] where given (``column_spread`` of the whole of which ``values`` are some
    rows). Drawn on ``generator``'s device."""
    std = column_spread(values) if std is None else std
    noise = torch.randn(values.shape, generator=generator, device=generator.device).to(values.device)
    return strength * std * noise


def column_spread(values: torch.Tensor) -> torch.Tensor:
    """[1, ...]: the standard deviation of each column of ``values`` [N, ...] over its N rows (0
    for a single row)."""
    return values.detach().std(dim=0, keepdim=True) if values.shape[0] > 1 else torch.zeros_like(values[:1])


def quantize_columns(values: torch.Tensor, bits: int) -> torch.Tensor:
    """``values`` [N, ...] rounded to 2**bits levels spread uniformly between each column's min and
    max (a constant column stays as it is)."""
    flat = values.reshape(values.shape[0], -1)
    lo, hi = flat.min(dim=0).values, flat.max(dim=0).values
    step = (hi - lo) / (2**bits - 1)
    safe = torch.where(step > 0, step, torch.ones_like(step))
    out = torch.where(step > 0, lo + torch.round((flat - lo) / safe) * safe, flat)
    return out.reshape(values.shape)


def sor_mask(xyz: torch.Tensor, neighbours: int, std_ratio: float) -> torch.Tensor:
    """[N] bool: statistical outliers of the points ``xyz`` [N, 3] (mean distance to the
    ``neighbours`` nearest others above the mean of that distance + std_ratio standard deviations)."""
    mean = mean_neighbour_distance(xyz, neighbours)
    return mean > mean.mean() + std_ratio * mean.std()


def mean_neighbour_distance(xyz: torch.Tensor, neighbours: int, among: torch.Tensor | None = None) -> torch.Tensor:
    """[N] mean distance of each point of ``xyz`` [N, 3] to its ``neighbours`` nearest other points
    (fewer when there are fewer), float64 on the CPU, returned on ``xyz``'s device. among: [N] bool,
    the points that count as neighbours (default: all)."""
    from sklearn.neighbors import NearestNeighbors

    points = xyz.detach().cpu().double().numpy()
    pool = points if among is None else points[among.cpu().numpy()]
    n = min(neighbours, pool.shape[0] - 1)
    if n < 1:
        return torch.zeros(points.shape[0], dtype=torch.float64, device=xyz.device)
    dist, _ = NearestNeighbors(n_neighbors=n + 1).fit(pool).kneighbors(points)
    # A point of the pool finds itself first, at distance 0: that column is skipped for it.
    inside = np.ones(points.shape[0], dtype=bool) if among is None else among.cpu().numpy()
    dist = np.where(inside[:, None], dist[:, 1:], dist[:, :n])
    return torch.from_numpy(dist.mean(axis=1)).to(xyz.device)


@torch.no_grad()
def anchor_opacity(model: ScaffoldModel, cameras: list[Camera]) -> torch.Tensor:
    """[N] total opacity of each anchor: the sum of its decoded public Gaussians' opacities (negative
    ones count as 0: they are not kept), averaged over ``cameras`` (the decoding depends on the view)."""
    n, k = model.anchors.num_anchors, model.anchors.n_offsets
    total = torch.zeros(n, device=model.device)
    for cam in cameras:
        total += decode_all(model.anchors, model.heads, cam)["neural_opacity"].clamp_min(0.0).view(n, k).sum(dim=1)
    return total / max(1, len(cameras))


def anchor_contribution(model: ScaffoldModel, cameras: list[Camera],
                        raster: RasterOptions | None = None) -> torch.Tensor:
    """[N] each anchor's alpha-weighted contribution to the public renders of ``cameras``: Σ over
    cameras, pixels and the anchor's Gaussians of T·α. A pixel is Σ_i T_i α_i c_i + T·background, so
    the gradient of the image's first channel summed over pixels with respect to Gaussian i's colour
    is exactly Σ_pixels T_i α_i; one backward pass per camera gives every Gaussian's share."""
    anchors = model.anchors
    total = torch.zeros(anchors.num_anchors, device=model.device)
    for cam in cameras:
        viewmat, K = camera_tensors(cam, model.device)
        with torch.no_grad():
            g = generate_neural_gaussians(anchors, model.heads, camera_center_from_viewmat(viewmat))
        colors = torch.ones_like(g["colors"]).requires_grad_(True)
        image, _, _ = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], colors, viewmat, K, cam.width,
                                cam.height, options=raster)
        image[..., 0].sum().backward()
        total.index_add_(0, g["anchor_index"], colors.grad[:, 0])
    return total


def purify_mask(model: ScaffoldModel, cameras: list[Camera], fraction: float, raster: RasterOptions | None = None,
                seed: int = 0) -> torch.Tensor:
    """[N] bool: the round(fraction·N) most suspicious anchors (see the module docstring, ``purify``)."""
    from sklearn.cluster import KMeans

    n = model.anchors.num_anchors
    contribution = torch.log1p(anchor_contribution(model, cameras, raster)).double().cpu()
    opacity = anchor_opacity(model, cameras).double().cpu()
    visible = contribution >= contribution.median()
    isolation = mean_neighbour_distance(model.anchors.xyz, ISOLATION_NEIGHBOURS, visible).double().cpu()
    features = torch.cat([model.anchors.xyz.detach().double().cpu(), contribution[:, None], opacity[:, None]], dim=1)
    features = _zscore(features)
    labels = KMeans(n_clusters=min(PURIFY_CLUSTERS, n), n_init=4, random_state=seed).fit(features.numpy()).labels_
    suspicion = (_zscore(-contribution) + _zscore(isolation)).numpy()
    cluster_suspicion = np.array([suspicion[labels == c].mean() for c in range(labels.max() + 1)])
    # lexsort: the last key sorts first (cluster suspicion, then the anchor's own), both descending
    order = np.lexsort((-suspicion, -cluster_suspicion[labels]))
    mask = torch.zeros(n, dtype=torch.bool)
    mask[torch.from_numpy(order[: round(fraction * n)])] = True
    return mask.to(model.device)


def _zscore(x: torch.Tensor) -> torch.Tensor:
    """Columns (or a vector) of ``x`` standardised; a constant column becomes 0."""
    std = x.std(dim=0)
    return (x - x.mean(dim=0)) / torch.where(std > 0, std, torch.ones_like(std))


# ---------------------------------------------------------------------------------------------
# The attacks
# ---------------------------------------------------------------------------------------------


def _prune(model: ScaffoldModel, mask: torch.Tensor) -> None:
    if bool(mask.all()):
        raise ValueError("the attack would remove every anchor")
    # No clamp of the Gaussians' base scales: that is a Scaffold-GS training rule, not part of pruning.
    model.anchors.prune_anchors(mask, max_log_gaussian_scale=None)


def _set(model: ScaffoldModel, name: str, value: torch.Tensor) -> None:
    with torch.no_grad():
        getattr(model.anchors, name).copy_(value)


def _finetune(model: ScaffoldModel, steps: int, ctx: AttackContext) -> None:
    from .train import ScaffoldTrainer

    if ctx.scene is None:
        raise ValueError(FINETUNE_NEEDS_SCENE)
    config = dataclasses.replace(ctx.train, iterations=steps, densify=False, raster=ctx.raster)
    trainer = ScaffoldTrainer(ctx.scene, config, device=model.device)
    trainer.start_from(model)
    while trainer.step_count < steps:
        trainer.step()


def apply_attack(model: ScaffoldModel, attack: Attack, ctx: AttackContext) -> dict:
    """Apply one attack to ``model`` in place; returns its report (attack, anchors before and after,
    ``applicable`` and, when it is not, ``reason``)."""
    anchors = model.anchors
    before = anchors.num_anchors
    report = {"attack": attack.text, "anchors_before": before, "applicable": True}
    name, args = attack.name, attack.args
    if name == "prune-random":
        _prune(model, random_prune_mask(before, args[0], ctx.generator, model.device))
    elif name == "prune-opacity":
        _prune(model, lowest_mask(anchor_opacity(model, ctx.cameras), args[0]))
    elif name.startswith("noise-"):
        attribute = {"noise-xyz": "xyz", "noise-feat": "feat", "noise-offset": "offsets"}[name]
        values = getattr(anchors, attribute)
        _set(model, attribute, values + column_noise(values, args[0], ctx.generator))
    elif name == "sor":
        _prune(model, sor_mask(anchors.xyz, *args))
    elif name == "quantize":
        for attribute in anchors.param_names:
            _set(model, attribute, quantize_columns(getattr(anchors, attribute).detach(), args[0]))
    elif name == "half":
        with torch.no_grad():
            for tensor in [getattr(anchors, a) for a in anchors.param_names] + list(model.heads.parameters()):
                tensor.copy_(tensor.half().float())
    elif name == "purify":
        _prune(model, purify_mask(model, ctx.cameras, args[0], ctx.raster,
                                  seed=int(torch.randint(2**31 - 1, (1,), generator=ctx.generator))))
    elif name == "finetune":
        _finetune(model, args[0], ctx)
    else:  # export-roundtrip
        report.update(applicable=False, reason=EXPORT_NOT_APPLICABLE)
    report["anchors_after"] = model.anchors.num_anchors
    return report


def apply_attacks(model: ScaffoldModel, attacks: list[Attack], ctx: AttackContext) -> list[dict]:
    """Apply ``attacks`` left to right to ``model`` in place; one report per attack."""
    if any(a.needs_scene for a in attacks) and ctx.scene is None:
        raise ValueError(FINETUNE_NEEDS_SCENE)
    return [apply_attack(model, attack, ctx) for attack in attacks]
