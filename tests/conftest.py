"""Shared test set-up: key seeds and random messages drawn from a seeded generator.

The product draws a bit decoder's seed (``secrets.token_hex`` in ``keyed_bits.new_seed``) and an
unspecified message (``secrets.randbits`` in ``payload``) from the operating system's secure source,
so every run of the suite would otherwise test other keys. Several tests train a few hundred
anchors, where a key can leave a bit with few voters, and a cut then with none (a bit without voters
reads undecided, which is the design's behaviour and counted by ``bits_without_voters``). Seeded
draws make a failure reproduce on any machine instead of turning up once in a few hundred runs.
Successive draws still differ, so tests of two keys still see two keys.
"""
import random

import pytest

from securegs_warp.secure import keyed_bits, payload

KEY_DRAWS_SEED = 20261129


class _SeededSecrets:
    """The part of the ``secrets`` module that ``keyed_bits`` and ``payload`` use, from a seeded generator."""

    def __init__(self, rng: random.Random):
        self._rng = rng

    def randbits(self, k: int) -> int:
        return self._rng.getrandbits(k)

    def token_hex(self, n_bytes: int) -> str:
        return self._rng.randbytes(n_bytes).hex()


@pytest.fixture(autouse=True, scope="session")
def seeded_key_draws():
    seeded = _SeededSecrets(random.Random(KEY_DRAWS_SEED))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(keyed_bits, "secrets", seeded)
        patch.setattr(payload, "secrets", seeded)
        yield
