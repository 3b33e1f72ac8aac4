"""``securegs`` command line. train, render, eval, export: the Scaffold-GS engine (cli.train);
hide, reveal, demo: SecureGS (cli.secure); audit: steganalysis (cli.audit); attack: attacks on a
release (cli.attack); verify: whether a release carries a key's message (cli.verify); what they
share: cli.common."""
from __future__ import annotations

import argparse
import functools
import sys
import time
import warnings
from pathlib import Path

from ..keys import KeyFileError
from . import attack, audit, secure, train, verify


def build_parser() -> argparse.ArgumentParser:
    from importlib.metadata import PackageNotFoundError, version

    try:
        release = version("securegs-warp")
    except PackageNotFoundError:
        release = "unknown"
    parser = argparse.ArgumentParser(prog="securegs", description=__doc__)
    parser.add_argument("--version", action="version", version=f"securegs-warp {release}")
    sub = parser.add_subparsers(dest="command", required=True)
    train.add_parsers(sub)
    secure.add_parsers(sub)
    audit.add_parsers(sub)
    attack.add_parsers(sub)
    verify.add_parsers(sub)
    return parser


_PACKAGE = Path(__file__).resolve().parents[1]


def _print_warning(show, message, category, filename, lineno, file=None, line=None):
    """This package's own warnings as one line for a person at a terminal (``warning: ...``); any
    other library's go to ``show``, the handler that was in place (Python's form names where they
    come from)."""
    if issubclass(category, UserWarning) and Path(filename).resolve().is_relative_to(_PACKAGE):
        print(f"warning: {message}", file=sys.stderr if file is None else file)
    else:
        show(message, category, filename, lineno, file, line)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = functools.partial(_print_warning, warnings.showwarning)
            code = args.func(args)
    except (ValueError, FileNotFoundError, KeyFileError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a full disk, a read-only folder: what was written before stays as it was
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    if code == 0 and not getattr(args, "quiet", False):
        print(f"done in {time.perf_counter() - t0:.1f} s")
    return code

