"""The ``fempdl`` command.

``fempdl run`` trains the default example, a network through a capped heat
layer (see :mod:`fempdl.heat_demo`), for a few caps K and with the converged
solver, and prints a table of the iterations used and the validation error.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

from fempdl import __version__


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _k_list(text: str) -> list[int]:
    try:
        return [_positive_int(part) for part in text.split(",") if part.strip()]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected comma-separated ints >= 1, got {text!r}") from err


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fempdl", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fempdl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train a network through a capped heat-step layer")
    run.add_argument("--k", type=_k_list, default=[4, 8, 16],
                     help="comma-separated Jacobi caps K to train with (default 4,8,16)")
    run.add_argument("--no-baseline", action="store_true",
                     help="skip the run trained with the converged solver")
    run.add_argument("--epochs", type=_positive_int, default=30)
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "run":
        from fempdl import heat_demo

        ks = list(args.k) + ([] if args.no_baseline else [None])
        progress = not args.no_progress and sys.stderr.isatty()
        results = [heat_demo.run(dataclasses.replace(heat_demo.HeatDemoConfig(), k=k, epochs=args.epochs,
                                                     seed=args.seed), progress=progress)
                   for k in ks]
        print(heat_demo.report(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
