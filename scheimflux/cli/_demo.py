"""`scheimflux demo`: the whole measurement chain on built-in simulated data."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="run the measurement chain end to end on built-in simulated data",
        description=__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--out", default="scheimflux-demo", help="folder for the demo's files")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--quick", action="store_true", help="fewer views and frames, no lens distortion"
    )
    p.set_defaults(func=run)


def run(args) -> int:
    from .._demo import run_demo

    run_demo(args.out, seed=args.seed, quick=args.quick)
    return 0
