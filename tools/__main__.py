"""``python -m tools <command> ...`` -- BulletTime4D's development tools (not shipped).

Each command module defines ``HELP``, ``add_arguments(parser)`` and ``main(args) -> int``,
like ``python -m engine``'s; modules are imported only when their command runs. The
diagnostics (``DIAGNOSTICS``) keep their own parsers: ``python -m tools phase-psnr --help``.
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
    "bench-cluster": "bench_cluster",
    "time-to-result": "time_to_result",
    "steps-curve": "steps_curve",
}

# diagnostics with their own argument parser: ``main(argv)`` gets the arguments after the command
DIAGNOSTICS = {
    "phase-psnr": "phase_psnr",            # eval PSNR by pixel class and place in the RGB interval
    "trajectory-error": "trajectory_error",  # moving objects' trajectory error against the generator's truth
    "spike-view-psnr": "spike_view_psnr",  # a run scored at the spike camera against the rendered light
    "orbit-strip": "orbit_strip",          # the +-30 degree orbit picture of docs/orbit_demo.png
    "static-error": "static_error",        # static pixels lost in front of the true surface or on it
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in DIAGNOSTICS:
        import importlib
        return int(importlib.import_module(f"{__package__}.{DIAGNOSTICS[argv[0]]}").main(argv[1:]) or 0)
    if argv in ([], ["-h"], ["--help"]):
        print("diagnostics (python -m tools NAME --help): " + ", ".join(DIAGNOSTICS))
    return run_commands("python -m tools", __doc__.splitlines()[0],
                        {name: f"{__package__}.{mod}" for name, mod in COMMANDS.items()}, argv)


if __name__ == "__main__":
    sys.exit(main())
