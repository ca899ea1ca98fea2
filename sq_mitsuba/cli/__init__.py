"""The ``sq-mitsuba`` command line: one parser, one subcommand per module in this package.

Each module ``sq_mitsuba/cli/<name>.py`` defines ``register(subparsers)``, which adds its
subcommand and sets ``func`` (taking the parsed ``argparse.Namespace``, returning an exit
code). Commands stay thin: they parse, call the library, and report. Heavy imports (Mitsuba)
happen inside the command, so ``sq-mitsuba --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

EXIT_ERROR = 2


class CLIError(Exception):
    """A user-facing failure: printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sq-mitsuba",
        description="Superquadric abstraction of spacecraft from single images, with Mitsuba 3.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        module.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (CLIError, ValueError, FileNotFoundError, PermissionError, OSError) as error:
        print(f"sq-mitsuba {args.command}: error: {error}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"sq-mitsuba {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
