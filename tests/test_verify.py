"""securegs verify: the keyed bit decoder, the statistic and its exact p-value, the command."""
import json
import math
import random

import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.keys import seal
from securegs_warp.secure.keyed_bits import SEED_BYTES, KeyedBitDecoder, keyed_uniform, new_seed
from securegs_warp.secure.verification import binomial_tail, verify_message

TINY = ["--width", "40", "--height", "30", "--train-views", "4", "--test-views", "1", "--quiet"]
MESSAGE = "101100111000111101011001001110100010110111001010"
CELL = 0.5  # the keyed grid's edge for positions spread over [0, 10]^3


def anchors(n: int = 2000, d: int = 32, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random features [n, d] and float32 positions [n, 3] (distinct)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, d, generator=g) * 0.3, torch.rand(n, 3, generator=g) * 10


def marked(decoder: KeyedBitDecoder, feat: torch.Tensor, xyz: torch.Tensor, margin: float = 0.5) -> torch.Tensor:
    """feat moved along each anchor's bit direction w until f·w = ±margin·|w|², the sign of its bit."""
    bit = decoder.anchor_bits(xyz)
    sign = torch.tensor([1.0 if c == "1" else -1.0 for c in decoder.message])[bit]
    w = decoder.directions[bit]
    along = (feat * w).sum(1) / (w * w).sum(1)
    return feat + (sign * margin - along)[:, None] * w


def test_binomial_tail_is_exact():
    assert binomial_tail(48, 48) == 2.0**-48
    assert binomial_tail(0, 48) == 1.0
    assert binomial_tail(3, 4) == 5 / 16
    assert binomial_tail(5, 4) == 0.0
    assert binomial_tail(200, 256) == pytest.approx(sum(math.comb(256, j) for j in range(200, 257)) / 2**256)


def test_decoder_is_derived_from_seed_and_message_only():
    seed = new_seed()
    a, b = KeyedBitDecoder(32, MESSAGE, seed, CELL), KeyedBitDecoder(32, MESSAGE, seed, CELL)
    assert torch.equal(a.directions, b.directions)
    # another message (a forger's choice) gives an unrelated decoder under the same seed
    other = KeyedBitDecoder(32, "0" + MESSAGE[1:], seed, CELL)
    assert not torch.equal(a.directions, other.directions)
    assert a.state_dict() == {}  # nothing but the seed and message needs storing
    u = keyed_uniform(seed, "x", (100_000,))
    assert -1 < float(u.min()) and float(u.max()) < 1 and abs(float(u.mean())) < 0.01
    with pytest.raises(ValueError, match="seed"):
        KeyedBitDecoder(32, MESSAGE, "00ff", CELL)
    with pytest.raises(ValueError, match="message"):
        KeyedBitDecoder(32, "0120", seed, CELL)


def test_each_anchor_keeps_its_bit_when_others_are_pruned():
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    _, xyz = anchors()
    bits = decoder.anchor_bits(xyz)
    keep = torch.rand(len(xyz), generator=torch.Generator().manual_seed(1)) > 0.2
    assert torch.equal(decoder.anchor_bits(xyz[keep]), bits[keep])
    assert set(bits.tolist()) == set(range(len(MESSAGE)))  # 2000 anchors give every bit voters


def test_anchor_bits_follow_the_positions_not_a_stale_copy():
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    _, xyz = anchors()
    fresh = lambda x: KeyedBitDecoder(32, MESSAGE, decoder.seed, CELL).anchor_bits(x)  # noqa: E731 (no history)
    bits = decoder.anchor_bits(xyz)
    assert torch.equal(decoder.anchor_bits(xyz.clone()), bits)  # same bytes: the kept bits
    xyz += 3.7 * CELL  # moved in place, across cells
    assert torch.equal(decoder.anchor_bits(xyz), fresh(xyz))
    assert not torch.equal(decoder.anchor_bits(xyz), bits)


def test_bits_survive_position_changes_smaller_than_the_cell():
    feat, xyz = anchors()
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    bits, mark = decoder.anchor_bits(xyz), marked(decoder, feat, xyz)
    lo, hi = xyz.min(0).values, xyz.max(0).values
    step = (hi - lo) / (2**10 - 1)
    quantized = torch.round((xyz - lo) / step) * step + lo  # what ``quantize:10`` does to positions
    half = xyz.half().float()
    for moved in (quantized, half):
        kept = float((decoder.anchor_bits(moved) == bits).float().mean())
        assert kept > 0.95  # a change of at most step/2 = 0.005 crosses a face of a 0.5 cell rarely
        assert verify_message(decoder, mark, moved).present
    # a move of a whole cell re-deals the anchors: the marked features then read as chance
    assert float((decoder.anchor_bits(xyz + CELL) == bits).float().mean()) < 0.1
    with pytest.raises(ValueError, match="cell"):
        KeyedBitDecoder(32, MESSAGE, new_seed(), 0.0)
    with pytest.raises(ValueError, match="NaN"):
        decoder.anchor_bits(torch.cat([xyz, torch.full((1, 3), float("nan"))]))


def test_projection_moves_only_the_features_that_disagree_and_only_along_their_bit():
    feat, xyz = anchors()
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    moved = decoder.project(feat, xyz, margin=1.0)
    logits, bit = decoder(moved, xyz)
    sign = torch.tensor([1.0 if c == "1" else -1.0 for c in MESSAGE])[bit]
    assert float((sign * logits).min()) >= 1.0 - 1e-4
    before, _ = decoder(feat, xyz)
    agreed = sign * before >= 1.0
    assert 0 < int(agreed.sum()) < len(feat) and torch.equal(moved[agreed], feat[agreed])
    delta = moved - feat
    w = decoder.directions[bit]
    along = (delta * w).sum(1, keepdim=True) / (w * w).sum(1, keepdim=True) * w
    assert torch.allclose(delta, along, atol=1e-5)  # the least move: along w_b only


def test_marked_features_are_present_and_unmarked_ones_are_fair_coins():
    feat, xyz = anchors()
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    result = verify_message(decoder, marked(decoder, feat, xyz), xyz)
    assert result.present and result.matched == 48 and result.p_value == 2.0**-48
    assert result.anchor_agreement == 1.0
    # Unmarked: the same features against 300 other keys. Matches are Binomial(48, 1/2): mean 24, sd
    # 3.46, so the mean of 300 lies within 0.6 (3 sd) of 24 unless something is biased. The keys are a
    # fixed sequence: fresh random ones made this bound fail about once in 370 runs by chance alone.
    keys = random.Random(0)
    matches, ps = [], []
    for _ in range(300):
        r = verify_message(KeyedBitDecoder(32, MESSAGE, keys.randbytes(SEED_BYTES).hex(), CELL), feat, xyz)
        assert not r.present
        matches.append(r.matched)
        ps.append(r.p_value)
    assert abs(sum(matches) / len(matches) - 24) < 0.6
    assert sum(p <= 0.05 for p in ps) <= 0.05 * 300 + 3 * math.sqrt(0.05 * 0.95 * 300)  # the p-value is valid
    # A container of another key (marked features) is unmarked for this key.
    assert not verify_message(KeyedBitDecoder(32, MESSAGE, new_seed(), CELL), marked(decoder, feat, xyz), xyz).present


def test_a_minority_of_moved_anchors_does_not_outvote_the_written_ones():
    """Anchors written just past a small margin (0.25, the robust default) and 45% of them moved
    into cells they were not written for: there they read directions they were never written for,
    with logits an order larger than the written ones' and random in sign. The majority of signs
    still reads every bit; a mean of sigmoids, which those logits dominate, does not."""
    feat, xyz = anchors(n=4000)
    decoder = KeyedBitDecoder(32, MESSAGE, "5e" * SEED_BYTES, CELL)  # a fixed key: the contrast is exact
    mark = marked(decoder, feat, xyz, margin=0.025)  # logits about 0.25
    moved = torch.rand(len(xyz), generator=torch.Generator().manual_seed(2)) < 0.45
    xyz_after = torch.where(moved[:, None], xyz + 7.5 * CELL, xyz)
    result = verify_message(decoder, mark, xyz_after)
    assert result.matched == 48
    logits, bit = decoder(mark, xyz_after)
    sigmoid_mean = torch.zeros(48).index_add_(0, bit, torch.sigmoid(logits)) / torch.bincount(bit, minlength=48)
    target = decoder.target
    assert int(((sigmoid_mean > 0.5).long() == target).sum()) < 48
    # (the moved anchors' logits are an order larger than the written ones')
    assert float(logits[moved].abs().median()) > 5 * float(logits[~moved].abs().median())


def test_blank_features_decide_no_bit():
    """Zero logits count half a vote each way, so a release of blank features leaves every bit
    undecided (none agrees), whatever the message's share of 0 bits."""
    _, xyz = anchors()
    decoder = KeyedBitDecoder(32, "0" * 48, new_seed(), CELL)
    vote, counts = decoder.vote(torch.zeros(len(xyz), 32), xyz)
    assert bool((counts > 0).all()) and bool((vote == 0.5).all())
    assert verify_message(decoder, torch.zeros(len(xyz), 32), xyz).matched == 0


def test_flipping_the_features_flips_every_vote_ties_included():
    """Negated features read as the same features under negated directions w_b: every bit's vote
    becomes 1 − vote exactly, also where its voters split evenly (the summed logits decide those),
    which is what keeps each decided bit of an unmarked model a fair coin."""
    feat, xyz = anchors(n=150)  # about 3 voters a bit: even splits are common
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    logits, bit = decoder(feat, xyz)
    positive = torch.zeros(48).index_add_(0, bit, (logits > 0).float())
    counts = torch.bincount(bit, minlength=48)
    assert bool(((positive * 2 == counts) & (counts > 0)).any())  # some bits tie on signs
    vote, _ = decoder.vote(feat, xyz)
    flipped, _ = decoder.vote(-feat, xyz)
    voted = counts > 0
    assert torch.allclose(flipped[voted], 1 - vote[voted], atol=1e-6)
    assert bool((vote[voted] != 0.5).all())  # every tie broken
    assert torch.equal(flipped[voted] > 0.5, vote[voted] < 0.5)  # every decision flips


def test_bits_without_voters_count_against_the_release():
    feat, xyz = anchors(n=10)
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    result = verify_message(decoder, marked(decoder, feat, xyz), xyz)
    assert result.matched <= 10 and not result.present
    assert result.bits_without_voters >= 48 - 10 and result.matched + result.bits_without_voters <= 48
    assert verify_message(decoder, *anchors()).bits_without_voters == 0  # 2000 anchors: every bit has voters


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny bit container and a plain model of the same scene and seed."""
    root = tmp_path_factory.mktemp("verify")
    assert main(["hide", "--out", str(root / "c"), "--payload", "bits:48", "--iterations", "40", *TINY]) == 0
    assert main(["train", "--out", str(root / "p"), "--iterations", "40", *TINY]) == 0
    return root


def verify_json(capsys, release, key, *extra) -> dict:
    capsys.readouterr()
    assert main(["verify", str(release), "--key", str(key), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_verify_container_and_plain_model(runs, capsys):
    key = runs / "c" / "key.safetensors"
    own = verify_json(capsys, runs / "c" / "public", key)
    assert {"present", "bit_accuracy", "p_value"} <= set(own)
    assert own["present"] is True and own["bit_accuracy"] == 1.0 and own["p_value"] < 1e-6
    plain = verify_json(capsys, runs / "p" / "model", key)  # not the key's release: an answer, not an error
    assert plain["present"] is False and plain["p_value"] > 1e-6
    assert main(["verify", str(runs / "c" / "public"), "--key", str(key)]) == 0
    assert capsys.readouterr().out.startswith("present: 48/48 bits agree")
    assert own["bits_without_voters"] == 0


def test_verify_names_the_bits_a_cut_release_has_no_anchor_for(runs, capsys, tmp_path):
    key = runs / "c" / "key.safetensors"
    assert main(["attack", str(runs / "c" / "public"), "--key", str(key), "--attack", "prune-random:0.99",
                 "--out", str(tmp_path / "cut"), "--device", "cpu"]) == 0
    cut = verify_json(capsys, tmp_path / "cut", key)
    assert cut["bits_without_voters"] > 0 and cut["matched"] + cut["bits_without_voters"] <= 48
    assert main(["verify", str(tmp_path / "cut"), "--key", str(key)]) == 0
    assert f"note: {cut['bits_without_voters']} of the 48 bits have no anchor in this release" in capsys.readouterr().out


def test_bad_keys_get_one_line_errors(runs, capsys, monkeypatch, tmp_path):
    key = runs / "c" / "key.safetensors"
    sealed = tmp_path / "key.sealed"
    sealed.write_bytes(seal(key.read_bytes(), "right"))
    monkeypatch.setenv("PASS", "wrong")
    cases = {
        "wrong passphrase": (["--key", str(sealed), "--passphrase-env", "PASS"], "wrong passphrase"),
        "a checkpoint": (["--key", str(runs / "c" / "checkpoint.pt")], "not a securegs key"),
        "missing": (["--key", str(tmp_path / "none")], "no such key file"),
        "bad alpha": (["--key", str(key), "--alpha", "2"], "alpha must lie in (0, 1)"),
    }
    for name, (args, message) in cases.items():
        capsys.readouterr()
        assert main(["verify", str(runs / "c" / "public"), *args]) == 2, name
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (name, err)
    monkeypatch.setenv("PASS", "right")
    assert verify_json(capsys, runs / "c" / "public", sealed, "--passphrase-env", "PASS")["present"] is True
    # reveal still refuses a key made for another release
    assert main(["reveal", str(runs / "p" / "model"), "--key", str(key), "--out", str(tmp_path / "r")]) == 2
    assert "belongs to another container" in capsys.readouterr().err


def test_study_counts_each_kind_of_test():
    """verification_rows on two synthetic containers and one plain model: every key meets every
    other model once (unmarked), its own container whole and pruned (marked) and shuffled."""
    from securegs_warp.model import AnchorModel
    from securegs_warp.secure.verification_study import StudyModel, random_prune, summary, verification_rows

    def model(name, seed, key):
        g = torch.Generator().manual_seed(seed)
        anchors = AnchorModel.from_points(torch.rand(3000, 3, generator=g) * 10, voxel_size=0.01)
        feat = torch.randn(anchors.num_anchors, 32, generator=g) * 0.3
        decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL) if key else None
        with torch.no_grad():
            anchors.feat.copy_(marked(decoder, feat, anchors.xyz) if key else feat)
        return StudyModel(name, "synthetic", seed, anchors, 0.0, decoder)

    models = [model("a", 0, True), model("b", 1, True), model("plain", 2, False)]
    pruned = random_prune(models[0].anchors, 0.2, torch.Generator().manual_seed(0))
    assert pruned.num_anchors == models[0].anchors.num_anchors - round(0.2 * models[0].anchors.num_anchors)
    rows = verification_rows(models, prunings=2, fraction=0.2)
    result = summary(rows)
    assert [result[k]["tests"] for k in ("unmarked", "marked", "shuffled")] == [4, 6, 4]
    assert result["marked"]["rate"] == 1.0 and result["unmarked"]["present"] == 0


def test_a_key_of_the_trained_bit_head_is_refused_in_one_line(runs, capsys, tmp_path):
    from securegs_warp.io import load_scaffold
    from securegs_warp.keys import save_key
    from securegs_warp.secure.container import release_fingerprint

    _, heads = load_scaffold(runs / "c" / "public")
    old = tmp_path / "old.safetensors"
    save_key(old, {"private.bit_mlp.0.weight": torch.zeros(32, 32)},
             {"heads": {"bits": 48, "offsets": False, "scale_offsets": True, "hidden": False}},
             release_fingerprint(heads))
    capsys.readouterr()
    assert main(["verify", str(runs / "c" / "public"), "--key", str(old)]) == 2
    err = capsys.readouterr().err.strip()
    assert "earlier securegs-warp" in err and len(err.splitlines()) == 1


def test_a_key_without_its_bit_cell_is_refused_in_one_line(runs, capsys, tmp_path):
    from securegs_warp.io import load_scaffold
    from securegs_warp.keys import save_key
    from securegs_warp.secure.container import release_fingerprint

    _, heads = load_scaffold(runs / "c" / "public")
    for name, extra in (("old", {}), ("bad", {"bit_cell": -1.0})):
        key = tmp_path / f"{name}.safetensors"
        save_key(key, {}, {"heads": {"message": "01" * 24, "bit_seed": "ab" * 32, "offsets": False,
                                     "scale_offsets": True, "hidden": False, **extra}}, release_fingerprint(heads))
        capsys.readouterr()
        assert main(["verify", str(runs / "c" / "public"), "--key", str(key)]) == 2
        err = capsys.readouterr().err.strip()
        assert str(key) in err and len(err.splitlines()) == 1
        assert ("earlier securegs-warp" if name == "old" else "bit cell") in err


def test_kept_projection_is_the_fresh_one_and_the_formula():
    feat, xyz = anchors()
    decoder = KeyedBitDecoder(32, MESSAGE, new_seed(), CELL)
    fresh = decoder.project(feat, xyz, margin=0.7)
    kept = decoder.project(feat, xyz, margin=0.7, projection=decoder.projection(xyz))
    assert torch.equal(fresh, kept)
    # The formula before the per-anchor constants were kept apart.
    bit = decoder.anchor_bits(xyz)
    w = decoder.directions[bit]
    sign = (decoder.target[bit] * 2 - 1).float()
    short = (0.7 - sign * 10.0 * (feat * w).sum(dim=1)).clamp_min(0)
    assert torch.equal(fresh, feat + (sign * short / (10.0 * (w * w).sum(dim=1)))[:, None] * w)


def test_an_object_key_answers_for_a_release_of_other_head_options(runs, capsys, tmp_path):
    # An object key's hidden decoder has the shapes of its own release's heads; a Scaffold-GS model
    # trained with the feature bank has others. verify reads the bit decoder alone: an answer.
    assert main(["hide", "--out", str(tmp_path / "o"), "--payload", "object+bits:48", "--iterations", "20",
                 *TINY]) == 0
    assert main(["train", "--out", str(tmp_path / "bank"), "--iterations", "20", "--feat-bank", *TINY]) == 0
    key = tmp_path / "o" / "key.safetensors"
    assert verify_json(capsys, tmp_path / "o" / "public", key)["present"] is True
    other = verify_json(capsys, tmp_path / "bank" / "model", key)
    assert other["present"] is False and other["p_value"] > 1e-6
