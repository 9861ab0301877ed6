"""``python -m tools <command> ...`` -- BulletTime4D's development tools (not shipped).

Each command module defines ``HELP``, ``add_arguments(parser)`` and ``main(args) -> int``,
like ``python -m engine``'s; modules are imported only when their command runs.
"""
from __future__ import annotations

import sys

from engine.cli import run_commands

# command name -> module under tools
COMMANDS = {
    "bench": "bench_cli",
    "stress": "stress",
    "ablate": "ablate",
    "bench-raster": "bench_raster",
    "bench-step": "bench_step",
    "bench-kernels": "bench_kernels",
    "bench-adam": "bench_adam",
    "bench-decode": "bench_decode",
    "import-graph": "import_graph",
    "compact-steps": "compact_steps",
    "gpu-check": "gpu_check",
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_commands("python -m tools", __doc__.splitlines()[0],
                        {name: f"{__package__}.{mod}" for name, mod in COMMANDS.items()}, argv)


if __name__ == "__main__":
    sys.exit(main())
