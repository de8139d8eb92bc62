"""`northfinder` command line: one module per subcommand, each with `register(subparsers)`.

A subcommand's `register` adds its parser and sets `func(args) -> int`. A
:class:`northfinder.errors.NorthfinderError` becomes one line on stderr and its exit code;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import NoReturn

# (module, subcommand) — modules are imported lazily so that a missing optional part does not
# break the others.
SUBCOMMANDS = ("find", "check", "replay", "align", "campaign", "history", "plan")


class OneLineParser(argparse.ArgumentParser):
    """argparse whose mistakes are one line (the command, what is wrong, where the help is), exit 2 —
    no usage block above it. Every subcommand's parser is one (add_subparsers takes the class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    from northfinder import __version__

    parser = OneLineParser(prog="northfinder", description="Find true north with a gyro.")
    parser.add_argument("--version", action="version", version=f"northfinder {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"northfinder.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"northfinder.cli.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from northfinder.errors import NorthfinderError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if getattr(args, "db", None):
            from northfinder.cli._common import apply_db_flag

            apply_db_flag(args)  # --db: the history every run of this command records into
        return int(args.func(args) or 0)
    except NorthfinderError as exc:
        print(f"northfinder: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("northfinder: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
