"""Sub-commands of ``python -m engine``; one module per command (see engine/__main__.py).

:func:`run_commands` is the one dispatcher, also used by ``python -m tools``: each command
module defines ``HELP``, ``add_arguments(parser)`` and ``main(args) -> int``, and is imported
only when its command runs, so ``--help`` and light commands start fast.
"""
from __future__ import annotations

import argparse
import importlib


def run_commands(prog: str, description: str, commands: dict[str, str], argv: list[str]) -> int:
    """Parse ``argv`` for ``prog`` and run the chosen command.

    ``commands``: command name -> absolute import name of its module. Only the requested
    sub-parser is built fully; the rest are listed by name for ``--help``. Returns the
    command's exit code, or 2 (after printing the help) when no command was given."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, module_name in commands.items():
        if name == wanted:
            module = importlib.import_module(module_name)
            p = sub.add_parser(name, help=module.HELP, description=module.HELP)
            module.add_arguments(p)
            p.set_defaults(_module=module)
        else:
            sub.add_parser(name, help=f"({prog} {name} --help)")
    args = parser.parse_args(argv)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    return int(args._module.main(args) or 0)
