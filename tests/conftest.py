"""Shared test set-up: key seeds and random messages drawn from a seeded generator.

The product draws a bit decoder's seed (``secrets.token_hex`` in ``keyed_bits.new_seed``) and an
unspecified message (``secrets.randbits`` in ``payload``) from the operating system's secure source,
so every run of the suite would otherwise test other keys. Several tests train a few hundred
anchors, where a key can leave a bit with few voters, and a cut then with none (a bit without voters
reads undecided, which is the design's behaviour and counted by ``bits_without_voters``). Here the
draws come from a generator seeded by the test's id (and, for a module's shared fixtures, by the
module's name), so a failure reproduces on any machine, run alone or in the suite, instead of
turning up by the luck of a draw. Successive draws still differ, so tests of two keys still see
two keys. Tests that run the CLI in a subprocess (``test_hiding_study``, parts of
``test_cli_safety``) still draw from the operating system.
"""
import random

import pytest

from securegs_warp.secure import keyed_bits, payload

KEY_DRAWS_SEED = 20261129


class _SeededSecrets:
    """The part of the ``secrets`` module that ``keyed_bits`` and ``payload`` use, from a seeded generator."""

    def __init__(self):
        self.rng = random.Random(KEY_DRAWS_SEED)

    def randbits(self, k: int) -> int:
        return self.rng.getrandbits(k)

    def token_hex(self, n_bytes: int) -> str:
        return self.rng.randbytes(n_bytes).hex()


_SEEDED = _SeededSecrets()


@pytest.fixture(autouse=True, scope="session")
def seeded_key_draws():
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(keyed_bits, "secrets", _SEEDED)
        patch.setattr(payload, "secrets", _SEEDED)
        yield


# Autouse fixtures of a scope are set up before the other fixtures of that scope: a module's shared
# fixtures draw after the module's reseed, a test's own draws after its reseed.
@pytest.fixture(autouse=True, scope="module")
def module_key_draws(seeded_key_draws, request):
    _SEEDED.rng.seed(f"{KEY_DRAWS_SEED}:{request.module.__name__}")


@pytest.fixture(autouse=True)
def test_key_draws(seeded_key_draws, request):
    _SEEDED.rng.seed(f"{KEY_DRAWS_SEED}:{request.node.nodeid}")
