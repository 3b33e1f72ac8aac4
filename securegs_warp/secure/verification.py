"""Does a release carry a key's message? The test ``securegs verify`` runs, with its p-value.

Null hypothesis: the release was not marked with this key (trained without it: a plain model, a
container made with another key). The key's bit decoder is derived from its seed and message alone
(``keyed_bits.py``), so under the null the decoder is independent of the release and each decoded
bit agrees with the message with probability 1/2, independently of the others. The number of
agreeing bits k of an L-bit message is then Binomial(L, 1/2), and the p-value is exact:

    p = P(Binomial(L, 1/2) >= k) = sum_{j >= k} C(L, j) / 2^L

No null statistics have to be estimated or stored: the randomness of the key is the null
distribution. A bit that no anchor of the release votes on counts as a disagreement, which only
makes the test conservative. The same p-value bounds forgery: a key drawn after seeing the release
matches it this well with probability p, so someone who tries K keys expects to reach about 1/K.
``scripts/verify_fpr.py`` checks the false-positive rate empirically (docs/results.md).
"""
from __future__ import annotations

import dataclasses
import math

import torch

from .keyed_bits import KeyedBitDecoder

# p-value at or below which a release is said to carry the message: a 48-bit message needs 41
# agreeing bits, and a marked container reads all 48 (p = 2^-48 = 3.6e-15). It must stay well
# below 1/K for the number of keys K a forger could try, which is why verify prints the p-value.
DEFAULT_ALPHA = 1e-6


@dataclasses.dataclass(frozen=True)
class Verification:
    """The outcome of testing one release against one key.

    present: p_value <= alpha. bit_accuracy: matched / bits. anchor_agreement: the fraction of the
    release's anchors whose own vote agrees with its bit of the message (about 0.5 when unmarked).
    bits_without_voters: bits that no anchor of the release carries (each counts as a disagreement):
    a release cut down to few anchors, or to few cells of the key's grid, leaves some.
    """

    present: bool
    bit_accuracy: float
    matched: int
    bits: int
    p_value: float
    alpha: float
    anchor_agreement: float
    anchors: int
    bits_without_voters: int

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def binomial_tail(k: int, n: int) -> float:
    """P(Binomial(n, 1/2) >= k): an integer sum over 2^n, divided once (correctly rounded)."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    return sum(math.comb(n, j) for j in range(max(k, 0), n + 1)) / 2**n


def min_p_value(bits: int) -> float:
    """The smallest p-value an L-bit message can reach (every bit agrees): 2^-L."""
    return 2.0**-bits


@torch.no_grad()
def verify_message(decoder: KeyedBitDecoder, feat: torch.Tensor, xyz: torch.Tensor,
                   alpha: float = DEFAULT_ALPHA) -> Verification:
    """Test anchors with features feat [N, d] at positions xyz [N, 3] against the decoder's message."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    message = decoder.target
    vote, counts = decoder.vote(feat, xyz)
    decided = (counts > 0) & (vote != 0.5)
    matched = int(((vote > 0.5).long() == message)[decided].sum())
    logits, bit = decoder(feat, xyz)
    agreement = float(((logits > 0).long() == message[bit]).float().mean()) if len(bit) else 0.0
    p = binomial_tail(matched, decoder.n_bits)
    return Verification(present=p <= alpha, bit_accuracy=matched / decoder.n_bits, matched=matched,
                        bits=decoder.n_bits, p_value=p, alpha=alpha, anchor_agreement=agreement,
                        anchors=int(feat.shape[0]), bits_without_voters=int((counts == 0).sum()))
