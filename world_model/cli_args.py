"""The command lines' argument types and output checks, shared by ``m4world``, ``python -m
world_model.train`` and the recipe: a malformed value is refused while the arguments are parsed
(argparse names the flag; the message names the value and what is allowed), before any work.

Import-light (no torch, no numpy) so that building a parser stays fast.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

# The largest seed a command takes: numpy's generators, torch.manual_seed (below 2**64) and
# gymnasium's reset all accept it with the small offsets the commands add (episode, row, step).
MAX_SEED = 2**63 - 1
OUTPUT_KINDS = ("file", "folder")


def _integer(text: str) -> int | None:
    try:
        return int(text)
    except ValueError:
        return None


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def positive_int(text: str) -> int:
    """An argparse type: ``0`` or ``-3`` would otherwise mean "the default" or fail deep in a stage."""
    value = _integer(text)
    if value is None or value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An argparse type for a count that may be zero (none)."""
    value = _integer(text)
    if value is None or value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or a positive integer, got {text!r}")
    return value


def seed(text: str) -> int:
    """An argparse type for a seed: an integer in ``[0, MAX_SEED]``."""
    value = _integer(text)
    if value is None or not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, 2**63 - 1], got {text!r}")
    return value


def positive_float(text: str) -> float:
    """An argparse type for a finite number above zero (a duration, a size, a rate)."""
    value = _number(text)
    if value is None or not value > 0:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """An argparse type for a finite number of at least zero (an extra loss weight)."""
    value = _number(text)
    if value is None or not value >= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of at least 0, got {text!r}")
    return value


def probability(text: str) -> float:
    """An argparse type for a probability: a number in [0, 1]."""
    value = _number(text)
    if value is None or not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1], got {text!r}")
    return value


def check_out(path: str | os.PathLike | None, kind: str, option: str = "--out") -> None:
    """Refuse an output path of the wrong kind (``kind``: a "file" or a "folder", created if
    missing) or in no writable folder, before any work is done (not after an hour of it)."""
    if kind not in OUTPUT_KINDS:
        raise ValueError(f"an output is one of {OUTPUT_KINDS}, not {kind!r}")
    if path is None:
        return
    p = Path(path)
    if kind == "file" and p.is_dir():
        raise ValueError(f"{option} {path} is a directory; give a file path")
    if kind == "folder" and p.exists() and not p.is_dir():
        raise ValueError(f"{option} {path} is a file; give a folder (it is created if missing)")
    parent = p.parent if kind == "file" else p
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise ValueError(f"{option} {path}: {parent} is not a writable folder")


def check_in_folder(path: str | os.PathLike, option: str) -> None:
    """Refuse an input folder that is not there (a missing one, or a file)."""
    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"{option} {path}: {'a file, not a folder' if p.exists() else 'no such folder'}")
