"""Headless BulletTime4D: capture -> reconstruction -> animated Gaussians -> bullet-time render.

Runs the add-on's own operators, exactly as the sidebar buttons do, without a UI:

    .venv/bin/python scripts/headless_example.py --capture demo_capture --out OUT --seconds 20
    blender --background --python scripts/headless_example.py -- --capture demo_capture --out OUT

1. ``bpy.ops.bt4d.import_capture``     cameras, frame rate and frame range from the capture
2. ``bpy.ops.bt4d.reconstruct``        trains (synchronously in background mode), evaluates
                                       on the held-out camera, brings the result back
3. ``bpy.ops.bt4d.add_orbit_camera``   orbit around the reconstruction, Capture Time frozen
                                       at the middle of the capture (bullet time)
4. ``bpy.ops.bt4d.render_path``        exact splat renders of the orbit, EXR or PNG
5. saves ``<out>/bullet_time.blend``   open it in Blender, or render it with Cycles/EEVEE

Outputs under ``--out``: ``runs/<capture>/`` (checkpoint, run.json, metrics),
``render/orbit_####.exr``, ``bullet_time.blend``; the last line printed is
``RESULT {json summary}``.

When the add-on is not enabled (plain ``bpy`` module, or Blender without the extension
installed) the script enables this checkout as a local extension (a symlink in a temp
extension repository called ``bt4d_local``; nothing is written to your preferences).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
LOCAL_REPO = "bt4d_local"


def parse_args(argv=None):
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capture", required=True, help="capture folder (transforms.json ...)")
    p.add_argument("--out", required=True, help="output folder (runs, renders, .blend)")
    p.add_argument("--seconds", type=float, default=60.0, help="training budget in seconds (default 60)")
    p.add_argument("--iterations", type=int, default=0, help="fixed training steps instead of --seconds")
    p.add_argument("--preset", default="fast", choices=("fast", "balanced", "quality"))
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--no-spikes", action="store_true", help="RGB only (ignore the spike stream)")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--frames", type=int, default=48, help="orbit length in frames (default 48)")
    p.add_argument("--turns", type=float, default=1.0, help="orbit revolutions (default 1)")
    p.add_argument("--freeze-at", type=float, default=None,
                   help="capture time (s) to freeze; default the middle of the capture")
    p.add_argument("--resolution-percentage", type=int, default=100)
    p.add_argument("--format", default="OPEN_EXR", choices=("OPEN_EXR", "PNG"))
    return p.parse_args(argv)


def ensure_addon():
    """Enable the add-on (this checkout) unless Blender already has it."""
    import bpy

    if "reconstruct" in dir(bpy.ops.bt4d):
        return None
    import addon_utils

    parent = Path(tempfile.mkdtemp(prefix="bt4d_ext_"))
    (parent / "bullettime4d").symlink_to(REPO_ROOT, target_is_directory=True)
    repos = bpy.context.preferences.extensions.repos
    if LOCAL_REPO not in [r.module for r in repos]:
        repos.new(name=LOCAL_REPO, module=LOCAL_REPO, custom_directory=str(parent), source="USER")
    else:
        next(r for r in repos if r.module == LOCAL_REPO).directory = str(parent)
    errors = []
    mod = addon_utils.enable(f"bl_ext.{LOCAL_REPO}.bullettime4d", default_set=False, handle_error=errors.append)
    if mod is None or errors:
        raise SystemExit(f"could not enable the BulletTime4D add-on: {errors}")
    return mod


def main(argv=None) -> int:
    args = parse_args(argv)
    import bpy

    t_start = time.monotonic()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    capture = Path(args.capture).resolve()

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    ensure_addon()

    # 1. import
    bpy.ops.bt4d.import_capture(directory=str(capture))
    scene = bpy.context.scene
    s = scene.bt4d
    s.preset, s.device, s.use_spikes = args.preset, args.device, not args.no_spikes
    s.output_dir = str(out / "runs")
    scene.bt4d_run.resume = not args.restart

    # 2. reconstruct (synchronous here), evaluate, bring back
    bpy.ops.bt4d.reconstruct(seconds=max(5.0, args.seconds), iterations=max(0, args.iterations))
    run = scene.bt4d_run
    if run.status != "FINISHED":
        print(f"reconstruction did not finish: {run.status} {run.message}", file=sys.stderr)
        return 1
    result = next(o for o in scene.objects if o.get("bt4d_result"))

    # 3. orbit with Capture Time frozen (bullet time)
    t0, t1 = result["bt4d_time_range"]
    freeze_at = 0.5 * (t0 + t1) if args.freeze_at is None else args.freeze_at
    from importlib import import_module

    addon = next(m for m in sys.modules if m.endswith("bullettime4d.bt4d_addon.gaussian_nodes"))
    gn = import_module(addon)
    scene.frame_start, scene.frame_end = 1, max(1, args.frames)
    scene.frame_set(scene.frame_start)
    gn.key_capture_time(result, [(scene.frame_start, freeze_at)])  # current frame shows freeze_at
    bpy.context.view_layer.objects.active = result
    bpy.ops.bt4d.add_orbit_camera(turns=args.turns)  # keys the orbit, freezes Capture Time here

    # 4. exact splat renders along the path
    scene.render.resolution_percentage = args.resolution_percentage
    scene.render.filepath = str(out / "render" / "orbit_####")
    bpy.ops.bt4d.render_path(file_format=args.format, load_back=False)
    ext = ".exr" if args.format == "OPEN_EXR" else ".png"
    frames = sorted(str(p) for p in (out / "render").glob(f"orbit_*{ext}"))

    # 5. a .blend to open / render with Cycles or EEVEE
    blend = out / "bullet_time.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    summary = {
        "run_dir": run.run_dir, "status": run.status, "steps": run.step,
        "num_gaussians": int(result.data["bt4d_num_gaussians"]), "time_samples": int(result.data["bt4d_num_samples"]),
        "metrics": {"psnr": run.metric_psnr, "ssim": run.metric_ssim} if run.has_metrics else None,
        "frozen_capture_time": freeze_at, "frames": frames, "blend": str(blend),
        "camera": scene.camera.name, "seconds": round(time.monotonic() - t_start, 1),
    }
    print("RESULT " + json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
