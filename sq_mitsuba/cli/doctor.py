"""``sq-mitsuba doctor``: versions, Mitsuba variant, LLVM and device, with a one-line verdict."""

from __future__ import annotations

import argparse

from sq_mitsuba.cli import CLIError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "doctor", help="print versions, Mitsuba variant, LLVM version and device",
        description="Check that a Mitsuba variant runs here; print what the renderer uses.")
    parser.add_argument("--render", action="store_true",
                        help="also render and differentiate one small silhouette, checked "
                             "against the sphere's exact projected area")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.render.doctor import diagnose

    rows, error = diagnose(render=args.render)
    for key, value in rows.items():
        print(f"{key:>14}: {value}")
    if error is not None:
        raise CLIError(error)
    print("ok: the renderer can run")
    return 0
