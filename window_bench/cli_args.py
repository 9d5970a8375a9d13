"""The argument types of ``bench``: each value is checked by argparse, before any work, and a
bad one is a one-line error naming the value and what is allowed. Shared by
:mod:`window_bench.cli` and the subcommands other packages add (``bench encoder``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import window_bench
from window_bench.harness.seeds import MAX_SEED


def env_id(value: str) -> str:
    if value not in window_bench.ENV_IDS:
        raise argparse.ArgumentTypeError(
            f"unknown env {value!r}; registered: {', '.join(window_bench.ENV_IDS)}")
    return value


def checked_number(cast, ok, allowed: str):
    """An argparse type: ``cast(value)`` that satisfies ``ok``, else a one-line error naming
    the value and the ``allowed`` range (``">= 1"``, ``"in (0, 1]"``)."""
    kind = "an integer" if cast is int else "a number"

    def parse(value: str):
        try:
            v = cast(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind}, got {value!r}") from None
        if not ok(v):
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {v}")
        return v
    return parse


def int_at_least(lo: int):
    return checked_number(int, lambda v: v >= lo, f">= {lo}")


def int_in(lo: int, hi: int):
    return checked_number(int, lambda v: lo <= v <= hi, f"in {lo}..{hi}")


positive = int_at_least(1)
seed = int_in(0, MAX_SEED)
workers = int_in(1, 64)   # evaluation processes: one per core is the most that helps


def clearance_mm(value: str) -> float:
    """``--clearance``: millimetres per side within the scene's range (0.5-20 mm)."""
    from window_bench.envs.scene import CLEARANCE_RANGE

    lo, hi = (1000.0 * v for v in CLEARANCE_RANGE)
    try:
        mm = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a number of millimetres") from None
    if not lo <= mm <= hi:
        raise argparse.ArgumentTypeError(f"{value} mm is outside the supported range "
                                         f"[{lo:g}, {hi:g}] mm per side")
    return mm


def out_file(value: str) -> str:
    """A file this user can create: checked before any work, not after it."""
    from window_bench.harness.files import check_out_dir

    try:
        check_out_dir(Path(value).parent)
        is_dir = Path(value).is_dir()
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--out ")) from None
    except OSError as e:   # e.g. a name longer than the file system allows
        raise argparse.ArgumentTypeError(f"{value}: cannot be used ({e.strerror})") from None
    if is_dir:
        raise argparse.ArgumentTypeError(f"{value} is a directory; give a file name")
    return value


def writable_dir(option: str):
    """An argparse type: a directory this user can write into or create (``option`` is how
    the error names it)."""
    def parse(value: str) -> str:
        from window_bench.harness.files import check_out_dir

        try:
            check_out_dir(value, option)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e).removeprefix(f"{option} ")) from None
        return value
    return parse


out_dir = writable_dir("--out")


def add_out_file(p, help: str, required: bool = False) -> None:
    """``--out FILE`` and ``--force``; :func:`main` refuses an existing FILE without --force."""
    p.add_argument("--out", type=out_file, required=required, help=help)
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.set_defaults(outputs=lambda args: [args.out] if args.out else [])


def choice(options, what: str):
    def parse(value: str) -> str:
        if value not in options:
            raise argparse.ArgumentTypeError(f"unknown {what} {value!r}; choose from "
                                             f"{', '.join(options)}")
        return value
    return parse


def dir_path(value: str) -> str:
    """A directory to read, or to create: never a path through an existing file."""
    probe = Path(value)
    try:
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
    except OSError as e:   # e.g. a name longer than the file system allows
        raise argparse.ArgumentTypeError(f"{value}: cannot be used ({e.strerror})") from None
    if probe.exists() and not probe.is_dir():
        where = "" if probe == Path(value) else f": {probe}"
        raise argparse.ArgumentTypeError(f"{value}{where} is a file, not a directory")
    return value
