"""The ``iarcs`` command line. Each sub-command lives in ``experiments/commands/<name>.py`` and
registers itself with ``register(subparsers)``; handlers raise :class:`CLIError` (or a ValueError /
FileNotFoundError / model-call error with a clear message) for bad input, which is printed without a
traceback."""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
import traceback
from pathlib import Path

#: Modules whose ``register(subparsers)`` adds sub-commands, in the order --help lists them.
COMMAND_MODULES = [
    "experiments.commands.data",
    "experiments.commands.train",
    "experiments.commands.demo",
    "experiments.commands.evaluate",
    "experiments.commands.compare",
    "experiments.commands.prior",
    "experiments.commands.augment",
    "experiments.commands.reward",
    "experiments.commands.generate",
    "experiments.commands.info",
]


#: Set to 1 to see the traceback behind a one-line error too.
TRACEBACK_ENV = "IARCS_TRACEBACK"


class CLIError(Exception):
    """A user error: printed as ``iarcs: error: <message>`` with exit status 2."""


#: argparse destinations naming files a command reads (and their flags): ``--out`` may be none of them.
INPUTS = {"src": "--in", "scenes": "--scenes", "floors": "--floors", "reference": "--reference",
          "program": "--program", "checkpoint": "--checkpoint", "base": "--base", "run": "--run"}


def check_out_is_not_an_input(args: argparse.Namespace) -> None:
    """Refuse ``--out`` naming a file the command reads: it would be overwritten before (or while) it is read."""
    out = getattr(args, "out", None)
    if not isinstance(out, str) or not out:
        return
    target = Path(out).expanduser().resolve()
    for dest, flag in INPUTS.items():
        values = getattr(args, dest, None)
        for value in values if isinstance(values, list) else [values]:
            if isinstance(value, str) and value and Path(value).expanduser().resolve() == target:
                raise CLIError(f"--out {out} is also the {flag} input: writing it would destroy what the command "
                               "reads; choose another output path")


def finite_float(text: str) -> float:
    """argparse ``type`` of a float flag: a finite number (``nan`` or ``inf`` would run and write NaN results)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def add_device_option(parser: argparse.ArgumentParser, what: str) -> None:
    """``--device``: where ``what`` runs (checked by :func:`agents.config.resolve_device`)."""
    parser.add_argument("--device", default=None,
                        help=f"where {what} runs: auto (a CUDA GPU when torch sees one, else the CPU), cpu, cuda "
                             "or cuda:N (default: auto, or the config's)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="iarcs", description="iARCS: controllable 3D indoor scene generation with agentic RL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def user_errors() -> tuple[type[Exception], ...]:
    """Exceptions whose message is meant for the user (evaluated only when something was raised)."""
    from rewards.agent import RewardSynthesisError
    from rewards.llm import LLMError

    return CLIError, FileNotFoundError, ValueError, LLMError, RewardSynthesisError


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command not in ("train", "pretrain") and int(os.environ.get("WORLD_SIZE", "1")) > 1:
            raise CLIError(f"iarcs {args.command} runs in one process; only `iarcs train` and `iarcs pretrain` run "
                           "data-parallel under torchrun (agents/distributed.py)")
        check_out_is_not_an_input(args)
        result = args.func(args)
    except user_errors() as err:
        if os.environ.get(TRACEBACK_ENV) == "1":  # a one-line message may hide a bug: its traceback on request
            traceback.print_exc()
        print(f"iarcs: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a folder that cannot be written, a path under a file, a full disk: one line, the path
        if isinstance(err, (FileExistsError, NotADirectoryError)) and err.filename and Path(err.filename).is_file():
            message = f"{err.filename} is a file, not a folder: choose an output path that is not under it"
        else:
            message = f"{err.strerror or err}: {err.filename}" if err.filename else str(err)
        print(f"iarcs: error: {message}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("iarcs: interrupted", file=sys.stderr)
        return 130
    except Exception:  # noqa: BLE001 -- not the user's input: a bug, shown whole
        traceback.print_exc()
        print("iarcs: internal error (a bug, not your input): please report it with the traceback above and the "
              "command you ran", file=sys.stderr)
        return 1
    return int(result or 0)


if __name__ == "__main__":
    # run the imported module's main, so that CLIError is the same class the commands raise
    from experiments.cli import main as _main

    sys.exit(_main())
