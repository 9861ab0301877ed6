"""``python -m tools <command> ...`` -- BulletTime4D's development tools (not shipped).

Each command module defines ``HELP``, ``add_arguments(parser)`` and ``main(args) -> int``,
like ``python -m engine``'s; modules are imported only when their command runs.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# command name -> module under tools
COMMANDS = {
    "bench": "bench_cli",
    "stress": "stress",
    "ablate": "ablate",
    "bench-raster": "bench_raster",
    "bench-decode": "bench_decode",
    "import-graph": "import_graph",
}


def _load(name: str):
    return importlib.import_module(f".{COMMANDS[name]}", package=__package__)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m tools", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name in COMMANDS:
        if name == wanted:
            module = _load(name)
            p = sub.add_parser(name, help=module.HELP, description=module.HELP)
            module.add_arguments(p)
            p.set_defaults(_module=module)
        else:
            sub.add_parser(name, help=f"(python -m tools {name} --help)")
    args = parser.parse_args(argv)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    return int(args._module.main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
