"""Private key files: the hidden heads (MLP weights) and their metadata, bound to one public container.

A key is a ``.safetensors`` file: named tensors (``offset_mlp.0.weight`` ...) plus string metadata
``format=securegs-key``, ``version=2``, ``container=<fingerprint>``, ``metadata=<json>`` and
``sha256=<checksum>`` over the tensors, the fingerprint and the metadata together (``reveal`` and
``verify`` read the message, the bit seed and the cameras from the metadata: editing them must be
detected like editing a weight). Version 1 keys, whose checksum covered the tensors alone, are still
read, since a key is the only way back to its secret. safetensors rather than ``torch.save`` because
a pickle runs code when it is loaded, and key files get passed around: reading a key must never
execute anything. Only safetensors and JSON are ever parsed here.

With a passphrase the same bytes are sealed in an envelope::

    SECUREGS-SEALED-KEY v1\\n
    {"cipher": "AES-256-GCM", "kdf": "scrypt", "n": 32768, "r": 8, "p": 1, "salt": ..., "nonce": ...}\\n
    <AES-256-GCM ciphertext of the plain key file, with its 16-byte tag>

The key is derived with scrypt (memory-hard, so guessing passphrases is slow) and both lines above
are the GCM associated data, so editing the salt, the KDF cost or the nonce is detected like editing
the ciphertext. All crypto comes from ``cryptography``; nothing here is home-made.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import struct
import unicodedata
import warnings
from pathlib import Path

import torch
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

from securegs_warp.io.atomic import atomic_write

FORMAT = "securegs-key"
VERSION = "2"
TENSORS_ONLY_VERSION = "1"  # its checksum covers the tensors alone (module docstring)
SEALED_MAGIC = b"SECUREGS-SEALED-KEY v1\n"
_SEALED_PREFIX = b"SECUREGS-SEALED-KEY "  # any version: lets us say "newer version" instead of "not a key"
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**15, 8, 1  # ~32 MiB, ~0.1 s per try: cheap once, costly per guess
# A forged header must not make us allocate gigabytes (scrypt takes 128·r·n bytes) or spend minutes
# (p runs) before the tag check: generous bounds around what ``seal`` writes.
_MAX_SCRYPT_BYTES = 2**28
_MAX_SCRYPT_P = 4


class KeyFileError(ValueError):
    """A key file cannot be used; the message names the file and says why in plain words."""


def _tensor_hash(tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 hex over sorted names, dtypes, shapes and raw (little-endian) bytes of ``tensors``."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().to("cpu").contiguous()
        # A JSON line per tensor with its byte count, then the bytes: no two different tensor sets
        # can produce the same stream (names and boundaries are unambiguous).
        head = {"name": name, "dtype": str(t.dtype), "shape": list(t.shape), "nbytes": t.nbytes}
        h.update(json.dumps(head, sort_keys=True).encode() + b"\n")
        # view(uint8) works for every dtype, bfloat16 included (numpy has no bfloat16).
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _checksum(tensors: dict[str, torch.Tensor], fingerprint: str, metadata_json: str) -> str:
    """SHA-256 hex binding a key's tensors, its container fingerprint and its metadata (as stored)."""
    bound = {"tensors": _tensor_hash(tensors), "container": fingerprint, "metadata": metadata_json}
    return hashlib.sha256(json.dumps(bound, sort_keys=True).encode()).hexdigest()


def container_fingerprint(public_state: dict[str, torch.Tensor]) -> str:
    """Identify a public container by its public MLP weights: ``{name: tensor}`` -> 64 hex chars.

    Pass the public MLP state dicts (not the anchors): noise or pruning of the point cloud leaves
    them unchanged, so a degraded container still matches its key, while another training does not.
    """
    return _tensor_hash(public_state)


def _plain_bytes(tensors: dict[str, torch.Tensor], metadata: dict, fingerprint: str) -> bytes:
    if not isinstance(fingerprint, str) or len(fingerprint) != 64:
        raise ValueError("fingerprint must be the 64-character hex string from container_fingerprint()")
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in tensors.items()):
        raise TypeError("tensors must map str names to torch.Tensor")
    # Own CPU copies: safetensors refuses non-contiguous tensors and tensors sharing storage.
    tensors = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    metadata_json = json.dumps(metadata, sort_keys=True, allow_nan=False)  # strict JSON, any reader
    header = {
        "format": FORMAT,
        "version": VERSION,
        "container": fingerprint,
        "metadata": metadata_json,
        "sha256": _checksum(tensors, fingerprint, metadata_json),
    }
    return _st_save(tensors, metadata=header)


def _derive(passphrase: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    # NFC so that the same typed passphrase gives the same bytes on every OS / keyboard.
    secret = unicodedata.normalize("NFC", passphrase).encode("utf-8")
    from cryptography.hazmat.primitives.kdf.scrypt import Scrypt  # only sealed keys need cryptography

    return Scrypt(salt=salt, length=32, n=n, r=r, p=p).derive(secret)


def seal(data: bytes, passphrase: str) -> bytes:
    """``data`` in the sealed envelope (module docstring): scrypt-derived AES-256-GCM, header
    authenticated. Also seals a sealed run's checkpoints, which hold the private heads."""
    if not passphrase:
        raise ValueError("an empty passphrase protects nothing; pass None for a plain key")
    salt, nonce = os.urandom(16), os.urandom(12)
    header = {"cipher": "AES-256-GCM", "kdf": "scrypt", "n": SCRYPT_N, "r": SCRYPT_R,
              "p": SCRYPT_P, "salt": base64.b64encode(salt).decode(),
              "nonce": base64.b64encode(nonce).decode()}
    prefix = SEALED_MAGIC + json.dumps(header, sort_keys=True).encode() + b"\n"
    key = _derive(passphrase, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P)
    from cryptography.hazmat.primitives.ciphers.aead import AESGCM

    return prefix + AESGCM(key).encrypt(nonce, data, prefix)


def is_sealed(blob: bytes) -> bool:
    """Whether ``blob`` starts like a sealed envelope (of any version)."""
    return blob.startswith(_SEALED_PREFIX)


def save_key(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict,
             fingerprint: str, passphrase: str | None = None) -> None:
    """Write a key file atomically, sealed with ``passphrase`` when one is given.

    tensors: ``{name: tensor}`` of the private heads (any dtype/device; stored as CPU copies).
    metadata: JSON-able dict (tuples come back as lists). fingerprint: ``container_fingerprint(...)``.
    The file is created owner-only (0600 on POSIX): it is a secret even when sealed.
    """
    data = _plain_bytes(tensors, metadata, fingerprint)
    if passphrase is not None:
        data = seal(data, passphrase)
    write_private(path, data)


def write_private(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` atomically to a file only its owner can read (0600 on POSIX) from the first byte."""
    def writer(f):
        if hasattr(os, "fchmod"):  # before any byte is written and before the rename publishes it
            os.fchmod(f.fileno(), 0o600)
        f.write(data)

    atomic_write(path, writer)


def unseal(path: Path, blob: bytes, passphrase: str | None, what: str = "key") -> bytes:
    """The plain bytes of a sealed envelope; KeyFileError naming ``path`` on a wrong passphrase, a
    modified file, an unknown version or a missing passphrase (``what`` names the file's role)."""
    if not blob.startswith(SEALED_MAGIC):
        first_line = blob.split(b"\n", 1)[0][:40].decode("ascii", "replace")
        raise KeyFileError(f"{path}: sealed {what} of an unknown version ({first_line!r}); "
                           "it needs a newer securegs-warp")
    end = blob.find(b"\n", len(SEALED_MAGIC))
    if end < 0:
        raise KeyFileError(f"{path}: sealed {what} is truncated or damaged (its header line is incomplete)")
    prefix, ciphertext = blob[: end + 1], blob[end + 1:]
    try:
        h = json.loads(prefix[len(SEALED_MAGIC):])
        salt, nonce = base64.b64decode(h["salt"], validate=True), base64.b64decode(h["nonce"], validate=True)
        n, r, p = int(h["n"]), int(h["r"]), int(h["p"])
        ok = (h["cipher"] == "AES-256-GCM" and h["kdf"] == "scrypt" and len(nonce) == 12
              and len(salt) >= 8 and n >= 2 and n & (n - 1) == 0 and r >= 1
              and 128 * r * n <= _MAX_SCRYPT_BYTES and 1 <= p <= _MAX_SCRYPT_P)
    except (ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        raise KeyFileError(f"{path}: sealed {what} header is damaged or uses an unsupported cipher")
    if passphrase is None:
        raise KeyFileError(f"{path}: this {what} is sealed with a passphrase; please give the passphrase")
    from cryptography.exceptions import InvalidTag
    from cryptography.hazmat.primitives.ciphers.aead import AESGCM

    try:
        return AESGCM(_derive(passphrase, salt, n, r, p)).decrypt(nonce, ciphertext, prefix)
    except InvalidTag:
        # GCM cannot tell these apart, and must not: either way nothing is trusted.
        raise KeyFileError(f"{path}: wrong passphrase, or the {what} file was modified (or truncated)") from None


def _parse_plain(path: Path, data: bytes) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """safetensors layout: u64 little-endian header size, JSON header, raw tensor bytes."""
    looks_safetensors = len(data) >= 9 and data[8:9] == b"{"
    n = struct.unpack("<Q", data[:8])[0] if looks_safetensors else 0
    if not looks_safetensors or n > 100_000_000:
        raise KeyFileError(f"{path}: not a securegs key file")
    if len(data) < 8 + n:
        raise KeyFileError(f"{path}: key file is truncated or damaged (its header is incomplete)")
    try:
        meta = json.loads(data[8: 8 + n]).get("__metadata__") or {}
    except (ValueError, AttributeError):
        raise KeyFileError(f"{path}: key file is damaged (its header is not valid JSON)") from None
    if not isinstance(meta, dict):
        raise KeyFileError(f"{path}: not a securegs key file (its safetensors metadata is not a mapping)")
    if meta.get("format") != FORMAT:
        raise KeyFileError(f"{path}: not a securegs key file (a safetensors file without key metadata)")
    if meta.get("version") not in (TENSORS_ONLY_VERSION, VERSION):
        raise KeyFileError(f"{path}: key file version {meta.get('version')!r} is unknown; "
                           f"this securegs-warp reads versions {TENSORS_ONLY_VERSION} and {VERSION}")
    try:
        tensors = _st_load(data)  # parses raw bytes only; never unpickles
    except Exception as e:  # SafetensorError is not exported under a stable name
        raise KeyFileError(f"{path}: key file is truncated or damaged ({e})") from None
    if meta.get("version") == TENSORS_ONLY_VERSION:
        expected = _tensor_hash(tensors)
    else:
        expected = _checksum(tensors, meta.get("container"), meta.get("metadata"))
    if meta.get("sha256") != expected:
        raise KeyFileError(f"{path}: the key file was modified (its contents do not match its checksum)")
    return meta, tensors


def load_key(path: str | os.PathLike, passphrase: str | None = None,
             expected_fingerprint: str | None = None) -> tuple[dict[str, torch.Tensor], dict]:
    """Read a key file -> ``(tensors {name: CPU tensor}, metadata dict)``; raise KeyFileError on any problem.

    Sealed and plain keys are told apart by the magic first line. A plain key given a passphrase
    loads (with a UserWarning: the caller believed it was protected). ``expected_fingerprint``,
    when given, must equal the container fingerprint stored in the key.
    """
    path = Path(path)
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        raise KeyFileError(f"{path}: no such key file") from None
    except OSError as e:
        raise KeyFileError(f"{path}: cannot read the key file ({e.strerror or e})") from None
    if is_sealed(blob):
        blob = unseal(path, blob, passphrase)
    elif passphrase is not None:
        warnings.warn(f"{path}: this key is not sealed; the passphrase was not needed", UserWarning,
                      stacklevel=2)
    meta, tensors = _parse_plain(path, blob)
    if expected_fingerprint is not None and meta.get("container") != expected_fingerprint:
        raise KeyFileError(f"{path}: this key belongs to another container "
                           f"(key is for {str(meta.get('container'))[:12]}…, "
                           f"container is {expected_fingerprint[:12]}…)")
    try:
        metadata = json.loads(meta.get("metadata", "{}"))
    except (ValueError, TypeError):
        raise KeyFileError(f"{path}: key file is damaged (its metadata is not valid JSON)") from None
    if not isinstance(metadata, dict):
        raise KeyFileError(f"{path}: key file is damaged (its metadata is not a JSON object)")
    return tensors, metadata
