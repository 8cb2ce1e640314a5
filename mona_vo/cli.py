"""Command line of mona-vo: parses options, calls one library function, prints. Imports are lazy so
that ``--help`` stays fast."""
from __future__ import annotations

import argparse
import sys

from mona_vo import __version__
from mona_vo.errors import MonaVoError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mona-vo", description=__doc__)
    p.add_argument("--version", action="version", version=f"mona-vo {__version__}")
    p.add_subparsers(dest="command")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return args.func(args)
    except MonaVoError as exc:
        print(f"mona-vo: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
