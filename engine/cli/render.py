"""``python -m engine render RUN --out DIR``: frames of a result from cameras, a camera path or an orbit.

Where the cameras come from (one of):

* ``--cameras FILE.json`` / ``--path FILE.json``: camera records (the capture's schema; the path
  that Blender's *Export Camera Path* writes is one, each frame at its own capture time);
* ``--orbit DEG``: a bullet-time arc of ``DEG`` degrees through the capture's first train camera,
  around the point it looks at (the median depth of the result in front of it), ``--views N``
  cameras with that camera's intrinsics.

At which capture time: each record's own, or ``--time T`` for every view (bullet time), or
``--times T0 T1``: from T0 to T1 over the views (slow motion while the camera moves). An orbit
without either is frozen at the middle of the result's time range.

``--video FILE.gif`` (Pillow) or ``FILE.mp4`` (imageio-ffmpeg, when installed) also writes the
frames as an animation at ``--fps``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..cluster.ray_runtime import ClusterError
from ..errors import CaptureError, RunError
from ..export.cached import load_result
from ..export.render_views import orbit_views, output_names, read_camera_file, write_renders
from ..io.capture import load_capture

HELP = "render a run along cameras, a camera path or a bullet-time orbit (EXR linear RGBA+Z or PNG sRGB)"


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory or compact cache (.bt4c)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--cameras", help="camera JSON (capture schema: cameras + frames)")
    src.add_argument("--path", help="a camera path JSON (as Blender's Export Camera Path writes it)")
    src.add_argument("--orbit", type=float, metavar="DEG",
                     help="an arc of DEG degrees (360: all round) through the capture's first train camera")
    p.add_argument("--views", type=int, default=60, help="cameras on the orbit (default 60)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--format", default="exr", choices=["exr", "png"], help="exr (default: linear RGBA + Z) or png")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--time", type=float, default=None, help="render every view at this capture time (bullet time)")
    when.add_argument("--times", type=float, nargs=2, metavar=("T0", "T1"), default=None,
                      help="capture times from T0 to T1 spread over the views (slow motion)")
    p.add_argument("--video", default=None, help="also write the frames as FILE.gif (or FILE.mp4 with imageio-ffmpeg)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of --video (default 30)")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when available), cpu, cuda, cuda:1")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--shards", type=int, default=1,
                   help="split the frames into N ranges rendered as Ray tasks (same files; needs Ray)")
    p.add_argument("--address", default=None,
                   help="with --shards: HOST:PORT of a running Ray cluster (default: a local Ray instance)")


def _first_train_view(scene, run):
    """The capture's first train camera as a View (its intrinsics and pose), or RunError."""
    cap_path = scene.info.get("capture")
    if not cap_path:
        raise RunError(Path(run), "the result records no capture: an orbit needs its cameras (use --cameras)")
    cap = load_capture(cap_path)
    frames = sorted(cap.train_frames(), key=lambda f: (f.time, f.camera))
    if not frames:
        raise CaptureError(Path(cap_path), "the capture has no train camera to start an orbit from")
    return cap.view(frames[0])


def orbit_from_result(scene, start, degrees: float, n: int, time: float) -> list:
    """``n`` views on an arc of ``degrees`` through ``start`` (a View), about its up axis, around
    the point it looks at: the median depth of the result's opaque Gaussians in front of it."""
    g = scene.gaussians_at(float(time))
    c2w = np.asarray(start.c2w, np.float64)
    eye, forward, up = c2w[:3, 3], -c2w[:3, 2], c2w[:3, 1]  # OpenGL camera axes
    depth = (np.asarray(g["means"], np.float64) - eye) @ forward
    keep = (depth > 0) & (np.asarray(g["opacities"]) > 0.5)
    d = float(np.median(depth[keep])) if keep.any() else 1.0
    return orbit_views(eye + d * forward, 0.0, start.intrinsics, n=n, time=time, up=tuple(up),
                       start_eye=eye, degrees=degrees)


def _views(args, scene) -> list:
    if args.orbit is not None:
        if not 0 < args.orbit <= 360:
            raise ValueError(f"--orbit must be in (0, 360] degrees, got {args.orbit:g}")
        if args.views < 1:
            raise ValueError(f"--views must be at least 1, got {args.views}")
        t0, t1 = scene.time_range
        t = args.time if args.time is not None else (args.times[0] if args.times else 0.5 * (t0 + t1))
        views = orbit_from_result(scene, _first_train_view(scene, args.run), args.orbit, args.views, t)
    else:
        views = read_camera_file(args.cameras or args.path)
    if args.times is not None:
        ts = np.linspace(args.times[0], args.times[1], len(views))
        for v, t in zip(views, ts):
            v.time = float(t)
    elif args.time is not None:
        for v in views:
            v.time = float(args.time)
    return views


def write_video(paths: list, target, fps: float) -> Path:
    """The frames ``paths`` (PNG or EXR) as an animated GIF (Pillow) or an MP4 (imageio-ffmpeg)."""
    from ..colour import linear_to_srgb
    from ..io.images import read_exr_channels, read_image_rgba

    target = Path(target)
    frames = []
    for p in paths:
        if Path(p).suffix == ".exr":
            ch = read_exr_channels(p)
            a = np.clip(ch["A"], 1e-6, 1.0)[..., None]
            lin = np.stack([ch["R"], ch["G"], ch["B"]], -1)
            rgb = linear_to_srgb(np.clip(lin / a, 0, 1)) * np.clip(ch["A"], 0, 1)[..., None]  # over black
        else:
            rgba = read_image_rgba(p)
            rgb = rgba[..., :3] * rgba[..., 3:4]  # straight alpha over black
        frames.append((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.suffix.lower() == ".gif":
        from PIL import Image

        ims = [Image.fromarray(f) for f in frames]
        ims[0].save(target, save_all=True, append_images=ims[1:], duration=max(1, round(1000.0 / fps)), loop=0)
        return target
    if target.suffix.lower() == ".mp4":
        try:
            import imageio_ffmpeg
        except ImportError as exc:
            raise ValueError(f"{target}: writing MP4 needs the imageio-ffmpeg package (pip install "
                             "imageio-ffmpeg); a .gif needs nothing more") from exc
        h, w = frames[0].shape[:2]
        writer = imageio_ffmpeg.write_frames(str(target), (w, h), fps=fps, macro_block_size=1)
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f))
        writer.close()
        return target
    raise ValueError(f"{target}: --video writes .gif or .mp4")


def _render_sharded(args, views, stems) -> list:
    """The frames over ``--shards`` Ray tasks (engine.cluster.render_shards): the same files."""
    from ..cluster.render_shards import render_sharded

    log = None if args.quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    res = render_sharded(args.run, views, stems, args.out, args.format, shards=args.shards, address=args.address,
                         device=args.device, log=log)
    if log:
        log(f"rendered {len(res['paths'])} frame(s) in {res['shards']} task(s): {res['seconds']:.1f} s "
            f"(+ {res['ray_start_seconds']:.1f} s to start Ray)")
    return [Path(p) for p in res["paths"]]


def main(args) -> int:
    try:
        if args.video and Path(args.video).suffix.lower() not in (".gif", ".mp4"):
            raise ValueError(f"{args.video}: --video writes .gif or .mp4")
        scene = load_result(args.run, device=args.device)
        views = _views(args, scene)
        paths = []
        names = [f"{i:06d}" for i in range(len(views))] if args.orbit is not None else None
        stems = output_names(views, names)  # refused before anything renders
        if args.shards > 1:
            paths = _render_sharded(args, views, stems)
        else:
            for i, (v, stem) in enumerate(zip(views, stems)):
                paths += write_renders(scene, [v], args.out, args.format, names=[stem])
                if not args.quiet:
                    print(f"render {i + 1}/{len(views)} t={v.time:.5f} s", file=sys.stderr, flush=True)
        if args.video:
            write_video(paths, args.video, args.fps)
    except (CaptureError, RunError, ValueError, ClusterError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {len(paths)} {args.format.upper()} file(s) to {args.out}"
          + (f" and {args.video}" if args.video else ""))
    return 0
