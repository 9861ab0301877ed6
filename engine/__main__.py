"""``python -m engine <command> ...`` — the engine's command line (no Blender needed).

Each sub-command lives in ``engine/cli/<name>.py`` and defines ``HELP``,
``add_arguments(parser)`` and ``main(args) -> int``. Modules are imported only when their
command runs, so ``--help`` and light commands start fast. Benchmarks, the stress suite
and the ablation are development tools: ``python -m tools`` (not shipped).
"""
from __future__ import annotations

import argparse
import importlib
import sys

# command name -> module under engine.cli
COMMANDS = {
    "train": "train",
    "eval": "evaluate",
    "render": "render",
    "export": "export",
    "demo": "demo",
    "spikes": "spikes",
}


def _load(name: str):
    return importlib.import_module(f".cli.{COMMANDS[name]}", package=__package__)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m engine", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # Build only the requested sub-parser fully; list the rest by name for --help.
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name in COMMANDS:
        if name == wanted:
            module = _load(name)
            p = sub.add_parser(name, help=getattr(module, "HELP", None), description=getattr(module, "HELP", None))
            module.add_arguments(p)
            p.set_defaults(_module=module)
        else:
            sub.add_parser(name, help=f"(python -m engine {name} --help)")
    args = parser.parse_args(argv)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    return int(args._module.main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
