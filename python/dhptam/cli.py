"""The ``dhptam`` command.

Every subcommand listed by ``dhptam --help`` works; new ones arrive with the features they
drive. Exit codes: 0 on success, 2 for usage and input errors (bad arguments, files, values),
1 for anything unexpected.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from . import __version__, _core
from .errors import DhptamError

EXIT_USAGE = 2


def _config_command(args: argparse.Namespace) -> int:
    if args.check is not None:
        config = _core.Config.from_file(Path(args.check))
        sys.stdout.write(f"# {args.check}: valid; resolved configuration follows\n")
        sys.stdout.write(config.to_commented_toml())
    else:
        sys.stdout.write(_core.Config.defaults_toml())
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``dhptam`` command."""
    parser = argparse.ArgumentParser(
        prog="dhptam",
        description="Stereo events+frames SLAM (DH-PTAM) with a Rust core.",
    )
    parser.add_argument("--version", action="version", version=f"dhptam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    config = sub.add_parser(
        "config",
        help="print the default configuration or check a configuration file",
        description=(
            "Print the full default configuration as documented TOML (--defaults, the default "
            "action), or validate a TOML file and print it resolved with the defaults (--check)."
        ),
    )
    group = config.add_mutually_exclusive_group()
    group.add_argument(
        "--defaults", action="store_true", help="print every key with its default and its meaning"
    )
    group.add_argument("--check", metavar="FILE", help="validate FILE and print the resolved configuration")
    config.set_defaults(func=_config_command)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except DhptamError as error:
        print(f"dhptam {args.command}: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"dhptam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover - exercised through the console script
    sys.exit(main())
