"""The bit decoder F_b†: a fixed function of the key, derived from a secret seed, never trained.

Why fixed: a decoder trained on the message learns to output the message from whatever features it
is given (a plain Scaffold-GS model decoded all 48 bits of a key made without it). A decoder drawn
from the key alone is independent of every model trained without that key, so on such a model each
decoded bit equals the message's bit with probability exactly 1/2, independently of the others:
the number of agreements is Binomial(L, 1/2), whatever the model (``verification.py``). The
container carries the message because training moves its anchor features until the decoder reads
the message from them.

The weights come from SHAKE-256 of the seed and the message, so a key stores only the seed (32
bytes) besides the message, and every machine and library version derives the same decoder.
``verify`` derives it from the key's seed and message, never from stored weights. So a forger who
wants a key for someone else's release cannot decode the release with a decoder of their choice and
call the result their message: every (seed, message) they try gives a new decoder, which reads
that message from an unmarked release no better than chance. A forger who tries K keys expects to
reach a p-value near 1/K, which is why ``verify`` reports the p-value and not only a decision.
"""
from __future__ import annotations

import hashlib
import math
import secrets
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

SEED_BYTES = 32
_DOMAIN = b"securegs-warp keyed bit decoder v1"
# Logits are LOGIT_SCALE times the projection of a feature on a unit-length direction: a margin of
# 1 (SecureConfig.bit_margin) puts a feature 0.1 past the decision plane.
LOGIT_SCALE = 10.0


def new_seed() -> str:
    """A fresh secret seed (hex) from the operating system's secure source."""
    return secrets.token_hex(SEED_BYTES)


def _stream(seed: str, label: str, n_bytes: int) -> bytes:
    try:
        raw = bytes.fromhex(seed)
    except (TypeError, ValueError):
        raise ValueError("the bit decoder's seed must be a hex string") from None
    if len(raw) != SEED_BYTES:
        raise ValueError(f"the bit decoder's seed must be {SEED_BYTES} bytes, got {len(raw)}")
    return hashlib.shake_256(_DOMAIN + b"\0" + raw + b"\0" + label.encode()).digest(n_bytes)


def keyed_uniform(seed: str, label: str, shape: tuple[int, ...]) -> torch.Tensor:
    """Float32 tensor of ``shape``, uniform in (-1, 1), from SHAKE-256(domain, seed, label).

    Each value comes from 4 bytes of the stream (24 bits used), so the values are symmetric about 0
    and independent to the hash's strength; the same seed gives the same tensor on every machine."""
    words = np.frombuffer(_stream(seed, label, 4 * math.prod(shape)), dtype="<u4") >> 8  # exact in float32
    values = (words.astype(np.float64) + 0.5) / 2**23 - 1.0
    return torch.from_numpy(values.astype(np.float32)).reshape(shape)


class BitProjection(NamedTuple):
    """Per-anchor constants of ``KeyedBitDecoder.project`` for N anchors: ``direction`` [N, d] (w of
    the anchor's bit), ``sign`` [N] (+1 for a 1 bit, −1 for a 0), ``scaled_sign`` [N] (LOGIT_SCALE ·
    sign), ``scaled_norm2`` [N] (LOGIT_SCALE · |w|²)."""

    direction: torch.Tensor
    sign: torch.Tensor
    scaled_sign: torch.Tensor
    scaled_norm2: torch.Tensor


class KeyedBitDecoder(nn.Module):
    """Per-anchor bit logits from anchor features, derived from ``seed`` and ``message``.

    Each anchor carries one bit of the message, chosen by a keyed hash of the cell that holds it in
    a grid of edge ``cell`` shifted by a keyed offset (positions are never trained, so pruning or
    saving leaves the survivors' bits unchanged, and so does moving a position by less than its
    distance to a cell face: quantisation, a float16 round trip, small position noise);
    bit b has a direction w_b [d] (``keyed_uniform``, unit length on average) and the anchor's logit
    is LOGIT_SCALE · w_b · f. One bit per anchor because every bit an anchor carries confines its
    feature to a half-space that the public heads must live with. No bias: blank features (f = 0) give
    logits 0, so the message is read from the features. Flipping w_b flips bit b's decision, and
    the w_b are independent: that is what makes the decoded bits of an unmarked model fair coin
    flips. Held as non-persistent buffers: the key stores the seed and the message, not these.
    """

    def __init__(self, feat_dim: int, message: str, seed: str, cell: float):
        super().__init__()
        if not message or set(message) - {"0", "1"}:
            raise ValueError(f"the message must be a non-empty string of 0 and 1, got {message!r}")
        if not (isinstance(cell, (int, float)) and math.isfinite(cell) and cell > 0):
            raise ValueError(f"the bit cell must be a positive length, got {cell!r}")
        self.seed, self.message, self.feat_dim, self.cell = seed, message, feat_dim, float(cell)
        directions = keyed_uniform(seed, f"directions:{message}", (len(message), feat_dim)) * 3.0**0.5
        self.register_buffer("directions", directions / feat_dim**0.5, persistent=False)
        self.register_buffer("target", torch.tensor([int(c) for c in message]), persistent=False)  # [L] 0/1
        self._mix = np.frombuffer(_stream(seed, f"anchors:{message}", 32), dtype="<u8") | np.uint64(1)
        # in [0, cell)^3: where the cell faces lie is part of the key
        self._offset = (keyed_uniform(seed, f"cell offset:{message}", (3,)).numpy().astype(np.float64) + 1) / 2 * self.cell
        self._last_bits = None  # (a copy of the float32 positions [N, 3] last hashed, their bits [N])

    @property
    def n_bits(self) -> int:
        return len(self.message)

    def anchor_bits(self, xyz: torch.Tensor) -> torch.Tensor:
        """The bit [N] (int64, 0..L-1) that each anchor at positions xyz [N, 3] (float32) carries.

        The last positions' bits are kept: anchors do not move during training (learning rate 0), so
        each step's projection asks again for the same positions, and comparing their bytes on the
        device costs less than copying them to the host and hashing them again."""
        last = self._last_bits
        if (last is not None and xyz.dtype == torch.float32 and last[0].shape == xyz.shape
                and last[0].device == xyz.device and torch.equal(last[0].view(torch.int32), xyz.detach().view(torch.int32))):
            return last[1]
        positions = xyz.detach().to("cpu", torch.float64).numpy()
        if not np.isfinite(positions).all():  # a NaN has no cell: it would be dealt an arbitrary bit
            raise ValueError("anchor positions hold NaN or inf: their bits are undefined")
        cells = np.floor((positions + self._offset) / self.cell)
        words = cells.astype(np.int64).view(np.uint64)
        with np.errstate(over="ignore"):  # arithmetic modulo 2^64 is the point
            h = (words[:, 0] * self._mix[0]) ^ (words[:, 1] * self._mix[1]) ^ (words[:, 2] * self._mix[2])
            h = (h ^ (h >> np.uint64(29))) * self._mix[3]
            h ^= h >> np.uint64(32)
        bits = torch.from_numpy((h % np.uint64(self.n_bits)).astype(np.int64)).to(xyz.device)
        if xyz.dtype == torch.float32:
            self._last_bits = (xyz.detach().clone(), bits)
        return bits

    def bits_without_voters(self, xyz: torch.Tensor) -> int:
        """How many bits of the message no anchor at positions xyz [N, 3] carries: each occupied cell
        carries one bit, so a model occupying few cells for the message's length leaves some, and
        each reads as undecided."""
        return int((torch.bincount(self.anchor_bits(xyz), minlength=self.n_bits) == 0).sum())

    def forward(self, feat: torch.Tensor, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(logits [N], the bit each anchor votes on [N] int64) of anchors with features feat [N, d]
        at positions xyz [N, 3]."""
        bit = self.anchor_bits(xyz)
        return LOGIT_SCALE * (feat * self.directions[bit]).sum(dim=1), bit

    @torch.no_grad()
    def projection(self, xyz: torch.Tensor) -> BitProjection:
        """What ``project`` needs of anchors at positions xyz [N, 3] (float32), whatever their features."""
        bit = self.anchor_bits(xyz)
        w = self.directions[bit]
        sign = (self.target[bit] * 2 - 1).to(w.dtype)
        return BitProjection(w, sign, sign * LOGIT_SCALE, LOGIT_SCALE * (w * w).sum(dim=1))

    @torch.no_grad()
    def project(self, feat: torch.Tensor, xyz: torch.Tensor, margin: float,
                projection: BitProjection | None = None) -> torch.Tensor:
        """The features [N, d] moved the least (in Euclidean distance) for every anchor's logit to
        agree with its bit by at least ``margin``: along w_b, and only where it does not yet.
        projection: ``projection(xyz)`` when the caller kept it (a trainer, between densifications:
        neither the anchors' bits nor a device-to-host read to confirm them are needed again)."""
        p = self.projection(xyz) if projection is None else projection
        short = (margin - p.scaled_sign * (feat * p.direction).sum(dim=1)).clamp_min(0)
        return feat + (p.sign * short / p.scaled_norm2)[:, None] * p.direction

    @torch.no_grad()
    def vote(self, feat: torch.Tensor, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(each bit's vote [L] in [0, 1]: the fraction of its voters whose logit is positive, a zero
        logit counting half, 0.5 when no anchor votes on it; each bit's number of voters [L] int64).
        Where the voters split evenly, the sign of their summed logits decides: the vote is then
        0.5 ± 1/(4·voters), between the tie and the nearest fraction, and stays 0.5 only where that
        sum is 0 too.

        A majority of signs, not a mean of sigmoids: a written anchor's logit sits just past the
        margin (sigmoid(0.25) = 0.56), while an anchor that an attack moved into another cell reads a
        direction it was never written for, where its logit is as large as the feature is long and
        random in sign. Its sigmoid is then near 0 or 1 and outweighs several written voters;
        its sign weighs as much as any one of them. A zero logit (blank features) counts half, so
        flipping w_b still flips bit b's vote exactly (``verification.py``), ties included, so on
        an unmarked model each decided bit stays a fair coin."""
        logits, bit = self(feat, xyz)
        counts = torch.bincount(bit, minlength=self.n_bits)
        positive = torch.zeros(self.n_bits, device=feat.device).index_add_(0, bit, 0.5 * (torch.sign(logits) + 1.0))
        summed = torch.zeros(self.n_bits, device=feat.device).index_add_(0, bit, logits)
        fraction = positive / counts.clamp_min(1)
        tie_break = 0.5 + torch.sign(summed) / (4 * counts.clamp_min(1))
        vote = torch.where(fraction == 0.5, tie_break, fraction)
        return torch.where(counts > 0, vote, torch.full_like(vote, 0.5)), counts
