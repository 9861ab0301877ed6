"""``python -m engine <command> ...`` — the engine's command line (no Blender needed).

Each sub-command lives in ``engine/cli/<name>.py`` and defines ``HELP``,
``add_arguments(parser)`` and ``main(args) -> int``. Modules are imported only when their
command runs, so ``--help`` and light commands start fast. Benchmarks, the stress suite
and the ablation are development tools: ``python -m tools`` (not shipped).
"""
from __future__ import annotations

import sys

from .cli import run_commands

# command name -> module under engine.cli
COMMANDS = {
    "train": "train",
    "eval": "evaluate",
    "render": "render",
    "export": "export",
    "demo": "demo",
    "spikes": "spikes",
    "batch": "batch",
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_commands("python -m engine", __doc__.splitlines()[0],
                        {name: f"{__package__}.cli.{mod}" for name, mod in COMMANDS.items()}, argv)


if __name__ == "__main__":
    sys.exit(main())
