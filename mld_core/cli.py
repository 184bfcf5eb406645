"""Command line: ``python -m mld_core <command> ...``.

Each feature module contributes its own sub-commands through a ``register(groups)`` function, so the
CLI stays a thin dispatcher. ``groups`` maps a group name to an argparse sub-parsers object:
``"root"`` (top level: generate, evaluate, bench, merge, models), ``"data"`` (data prepare ...), ``"train"``
(train vae|denoiser|evaluator). A registered parser sets ``func=callable(args) -> int``.
Errors meant for the user are raised as ``UsageError`` and printed without a traceback (exit 2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from mld_core.inputs import (MAX_SIDE_REDRAWS, MAX_VERB_REDRAWS, InputError, check_device, check_seed, check_threads,
                             int_in_range)

# Shared by generate, evaluate and bench (names here so that building the parser needs no torch).
PRECISION_CHOICES = ("fp32", "bf16")
PRECISION_HELP = ("denoiser precision: fp32 (default) or bf16 (faster on CPUs with AVX512-BF16 or AMX; samples "
                  "close to but not equal to fp32's)")

DEVICE_HELP = "cpu (default), cuda, mps or auto (CUDA, then MPS, then the CPU)"

# Modules that contribute commands. A module listed here that is missing is skipped, so the CLI
# keeps working while parts are being built.
COMMAND_MODULES = (
    "mld_core.data.cli",
    "mld_core.training.cli",
    "mld_core.generate",
    "mld_core.eval.cli",
    "mld_core.bench",
    "mld_core.shards",
    "mld_core.model_list",
)


class UsageError(Exception):
    """A problem with the user's input: printed as one message, exit code 2."""


def check_common_options(args) -> None:
    """Options several commands share, checked by one rule before any command runs."""
    if getattr(args, "threads", None) is not None:
        check_threads(args.threads, "--threads")
    if isinstance(getattr(args, "seed", None), int):
        check_seed(args.seed, what="--seed")
    if getattr(args, "side_redraws", None) is not None:
        int_in_range(args.side_redraws, "--side-redraws", 0, MAX_SIDE_REDRAWS)
    if getattr(args, "verb_redraws", None) is not None:
        int_in_range(args.verb_redraws, "--verb-redraws", 0, MAX_VERB_REDRAWS)
    if getattr(args, "device", None) is not None:  # cpu, cuda, mps or auto: resolved to what torch will use
        args.device = check_device(args.device, "--device")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m mld_core", description=__doc__.splitlines()[0])
    root = parser.add_subparsers(dest="command", metavar="COMMAND")
    data = root.add_parser("data", help="prepare training folders").add_subparsers(dest="data_command", metavar="ACTION")
    train = root.add_parser("train", help="train a model stage").add_subparsers(dest="train_command", metavar="STAGE")
    groups = {"root": root, "data": data, "train": train}
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue
            raise
        module.register(groups)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    formatwarning, warnings.formatwarning = warnings.formatwarning, _warning_line
    try:
        check_common_options(args)
        return int(func(args) or 0)
    except (UsageError, InputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = formatwarning


def _warning_line(message, category, filename, lineno, line=None) -> str:
    """A library warning as the command line's others are: one ``warning:`` line, no source location."""
    return f"warning: {message}\n"


if __name__ == "__main__":
    raise SystemExit(main())
