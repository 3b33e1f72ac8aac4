"""``securegs verify``: does a release carry a key's message? A decision, the bit accuracy and an
exact p-value under "this release was not marked with this key" (secure/verification.py)."""
from __future__ import annotations

import json

from ..secure.container import open_bit_decoder
from ..secure.verification import DEFAULT_ALPHA, min_p_value, verify_message
from . import common
from .common import CommandError
from .secure import passphrase_from


def cmd_verify(args) -> int:
    device = common.resolve_device(args.device)
    anchors, decoder = open_bit_decoder(args.release, args.key, passphrase_from(args), device=device)
    if decoder is None:
        raise CommandError(f"{args.key}: this key hides no bits, so there is no message to verify")
    result = verify_message(decoder, anchors.feat, anchors.xyz, args.alpha)
    if args.json:
        print(json.dumps(result.to_json()))
        return 0
    verdict = "present" if result.present else "absent"
    print(f"{verdict}: {result.matched}/{result.bits} bits agree (bit accuracy {result.bit_accuracy:.3f}), "
          f"p-value {result.p_value:.3g} (alpha {result.alpha:g}); {result.anchor_agreement:.3f} of "
          f"{result.anchors} anchors vote with the message")
    if result.bits_without_voters:
        print(f"note: {result.bits_without_voters} of the {result.bits} bits have no anchor in this release, and count "
              f"as disagreeing")
    if min_p_value(result.bits) > result.alpha:
        print(f"note: a {result.bits}-bit message cannot reach alpha {result.alpha:g} (its smallest p-value is "
              f"{min_p_value(result.bits):.3g}); hide more bits")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("verify", help="decide whether a release carries a key's message, with a p-value")
    p.add_argument("release", help="the release folder (point_cloud.ply + MLPs); any Scaffold-GS model")
    p.add_argument("--key", required=True, help="the key file holding the message")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                   help=f"p-value at or below which the message counts as present (default: {DEFAULT_ALPHA:g})")
    p.add_argument("--json", action="store_true", help="print one JSON object (present, bit_accuracy, p_value, ...)")
    p.add_argument("--device", help="cpu or cuda[:N] (default: cuda when available)")
    p.set_defaults(func=cmd_verify, quiet=True)
