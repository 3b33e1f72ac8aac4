"""Robust training: the hidden branch trains on randomly attacked copies of the anchors, so that the
payload survives those attacks on the release (``SecureConfig.robust``).

A robust spec joins attack specs with ``+`` (``prune-random:0.3+noise-feat:0.2+quantize:8``); each
step draws a strength for each of them: a fraction or σ uniformly in [0, the given value], and for
``quantize:B`` a bit depth uniformly in B..16. Only attacks on what the hidden branch reads are
offered: anchor dropout at random (``prune-random``) or of the anchors with the least public
opacity (``prune-opacity``: among the anchors the step's public render decoded, by the total opacity
of their public Gaussians in that view), noise on positions and features, quantisation of positions,
features and scalings. The hidden branch never reads the public offsets, so
``noise-offset`` has nothing to train against. The perturbed anchors feed the hidden render and the
bit loss only; the public render reads the anchors themselves, so the cover is trained as before.
"""
from __future__ import annotations

import dataclasses

import torch

from ..attacks import ATTACK_NAMES, ATTACK_SYNTAX, Attack, column_noise, lowest_mask, quantize_columns, random_prune_mask
from ..model.anchors import AnchorSizes

ROBUST_ATTACKS = ("prune-random", "prune-opacity", "noise-xyz", "noise-feat", "quantize")
# How each is written, for messages and help: ATTACK_SYNTAX restricted to them.
ROBUST_SYNTAX = ", ".join(s for s, n in zip(ATTACK_SYNTAX, ATTACK_NAMES) if n in ROBUST_ATTACKS)
QUANTIZE_MAX_BITS = 16
# The attacks whose strength is drawn on the anchors' device (the others need a host number: a count
# of the least opaque anchors, a bit depth).
DEVICE_DRAWN = ("prune-random", "noise-xyz", "noise-feat")


def parse_robust(text: str, option: str = "robust") -> list[Attack]:
    """``A+B+...`` -> attacks; refuses unknown specs, repeats and attacks the hidden branch cannot
    train against, in one line naming ``option`` (the config field that holds ``text``) and the
    attacks it can."""
    attacks = []
    for part in text.split("+"):
        name = part.strip().split(":")[0]
        if name in ATTACK_NAMES and name not in ROBUST_ATTACKS:
            why = " (the hidden branch does not read the public offsets)" if name == "noise-offset" else ""
            raise ValueError(f"{option}: {part.strip()} cannot be trained against{why}; use "
                             f"{', '.join(ROBUST_ATTACKS)} joined with +")
        try:
            attacks.append(Attack.parse(part, ROBUST_ATTACKS))
        except ValueError as error:
            raise ValueError(f"{option}: {error} (joined with +)") from None
    names = [a.name for a in attacks]
    if len(set(names)) != len(names):
        raise ValueError(f"{option} {text!r} names an attack twice")
    return attacks


@dataclasses.dataclass
class PerturbedAnchors(AnchorSizes):
    """What the hidden decoding reads of an ``AnchorModel``, perturbed for one step. Tensors are N
    rows (the anchors' own N: dropout is ``keep``, not removal, so indices match the model's), or S
    with ``serving_rows`` (N below reads S). Gradients flow through the perturbations to the tensors
    they were made from: the model's parameters, or a replayed step's row buffers.

    xyz [N, 3], feat [N, d], offsets [N, k, 3], scaling [N, 6], rotation [N, 4], opacity [N, 1];
    keep: [N] bool, the anchors this step's hidden branch may use (None: all).

    serving_rows: True where the tensors hold a key's S serving anchors only, in the order of its
    serving index, instead of the model's N (a replayed hidden branch's buffers,
    ``secure.hidden_graph``): the key decodes every row. spread: attribute name -> [1, ...], the
    standard deviation of that attribute's columns over the model's N anchors, which scales noise
    on these rows (None, or a name missing: their own columns' spread). registered: [P] long,
    ascending, where xyz holds a model's positions registered with its key's record
    (``SecureModel._key_anchors``, no perturbation; moved back onto it, or left in place where only
    an anchor the key never served was moved inside its radius): the anchors paired with an entry,
    which alone the key serves (``PrivateHeads.register``); None otherwise.
    """

    xyz: torch.Tensor
    feat: torch.Tensor
    offsets: torch.Tensor
    scaling: torch.Tensor
    rotation: torch.Tensor
    opacity: torch.Tensor
    keep: torch.Tensor | None = None
    serving_rows: bool = False
    spread: dict | None = None
    registered: torch.Tensor | None = None


def perturb(anchors, attacks: list[Attack], generator: torch.Generator,
            public_opacity: torch.Tensor | None = None, draws: torch.Generator | None = None) -> PerturbedAnchors:
    """One draw of ``attacks`` (from ``parse_robust``) on an ``AnchorModel``'s tensors (or on
    ``PerturbedAnchors``, a replayed step's serving rows: dropout then drops that fraction of them), in order.

    public_opacity: [N] total public opacity of each anchor in this step's view, NaN for anchors
    the view did not decode (needed by ``prune-opacity``). Masks, noise and the strengths of the
    DEVICE_DRAWN attacks are drawn from ``draws`` (default: a generator on the anchors' device
    seeded from ``generator``, or ``generator`` itself where the anchors are on its device); the
    other attacks' strengths from ``generator``. Perturbing with only DEVICE_DRAWN attacks reads
    nothing back to the host (``secure.hidden_graph`` captures it)."""
    view = dataclasses.replace(anchors) if isinstance(anchors, PerturbedAnchors) else \
        PerturbedAnchors(anchors.xyz, anchors.feat, anchors.offsets, anchors.scaling, anchors.rotation, anchors.opacity)
    draws = _device_generator(generator, view.xyz.device) if draws is None else draws
    for attack in attacks:
        if attack.name in DEVICE_DRAWN:
            # Drawn where the masks and noise are: no host number, so a CUDA graph can replay it.
            u = torch.rand((), generator=draws, device=draws.device)
        else:  # a count or a bit depth the host needs
            u = float(torch.rand((), generator=generator))
        if attack.name == "prune-random":
            dropped = random_prune_mask(view.num_anchors, u * attack.args[0], draws, view.xyz.device)
            view.keep = ~dropped if view.keep is None else view.keep & ~dropped
        elif attack.name == "prune-opacity":
            dropped = _least_opaque(public_opacity, u * attack.args[0])
            view.keep = ~dropped if view.keep is None else view.keep & ~dropped
        elif attack.name in ("noise-xyz", "noise-feat"):
            name = attack.name.removeprefix("noise-")
            values = getattr(view, name)
            spread = (view.spread or {}).get(name)
            setattr(view, name, values + column_noise(values, u.to(values.device) * attack.args[0], draws, spread))
        else:  # quantize: straight through, so the parameters still get the gradient of the quantised values
            bits = attack.args[0] + int(u * (QUANTIZE_MAX_BITS - attack.args[0] + 1))
            for name in ("xyz", "feat", "scaling"):
                values = getattr(view, name)
                setattr(view, name, values + (quantize_columns(values.detach(), min(bits, QUANTIZE_MAX_BITS))
                                              - values.detach()))
    return view


def _device_generator(generator: torch.Generator, device: torch.device) -> torch.Generator:
    """``generator`` where it is on ``device``'s kind, else one there seeded from it: a step's masks
    and noise drawn where the anchors are (drawing N·d normals on the host and copying them costs
    milliseconds per step on CUDA), and still reproducible from ``generator``'s state."""
    if torch.device(device).type == generator.device.type:
        return generator
    seed = int(torch.randint(2**62, (), generator=generator))
    return torch.Generator(device).manual_seed(seed)


def _least_opaque(public_opacity: torch.Tensor, fraction: float) -> torch.Tensor:
    """[N] bool: the round(fraction·V) anchors of least ``public_opacity`` [N] among the V that are
    not NaN."""
    decoded = (~torch.isnan(public_opacity)).nonzero()[:, 0]
    dropped = torch.zeros_like(public_opacity, dtype=torch.bool)
    dropped[decoded[lowest_mask(public_opacity[decoded], fraction)]] = True
    return dropped


@torch.no_grad()
def public_opacity(gaussians: dict, anchors) -> torch.Tensor:
    """[N] total opacity of each anchor's public Gaussians in one render (``generate_neural_gaussians``
    output ``gaussians``: negative opacities count as 0), NaN for anchors the render did not decode."""
    total = torch.full((anchors.num_anchors,), float("nan"), device=anchors.xyz.device)
    total[gaussians["visible_mask"]] = gaussians["neural_opacity"].clamp_min(0.0).view(-1, anchors.n_offsets).sum(1)
    return total
