"""An orbit of +-30 degrees around a result, rendered with ``bpy.ops.bt4d.render_path``, as a
labelled strip of frames and a per-frame coverage table (issue 14).

    make demo                                         # or: python -m engine demo --out runs/demo
    nice -n 10 .venv/bin/python tools/orbit_strip.py --run runs/demo

Runs with the ``bpy`` module from the venv (or ``blender --background --python
tools/orbit_strip.py -- --run ...``), through the add-on's own operators, as a user would:

1. ``bpy.ops.bt4d.import_capture``  the capture's cameras (the stereo pair) and resolution
2. ``bpy.ops.bt4d.load_result``     the run as animated Gaussians
3. a camera keyed on an arc around the point the stereo pair looks at (the closest point
   of the two train cameras' optical axes): azimuth ``-degrees -> +degrees`` about the
   world's up axis, at the pair's distance and height (azimuth 0 = the middle of the pair;
   + = towards its right), one key per frame; Capture Time keyed linearly over the whole
   capture (``--time sweep``, the default: both the orbit and the motion show) or frozen
   at the middle (``--time freeze``, bullet time)
4. ``bpy.ops.bt4d.render_path`` twice: EXR (the raw premultiplied render: its alpha says
   what the Gaussians cover) and opaque PNG (what a viewer sees: holes filled, as the
   operator does for opaque PNG)
5. with ``--prune-unobserved`` the same twice more with render_path's "Drop Unobserved
   Gaussians" (``engine.scene.observed``: those no train camera saw inside its image)
6. a strip of the frames every ``--label-step`` degrees (per variant two rows: the PNG,
   then the raw render over magenta, so what nothing covers shows) and a Markdown table
   per frame: coverage (share of pixels with alpha > 0.5 in the raw render), holes (the
   rest) and the share of near-black pixels in the PNG.

Outputs: ``<out>/exr/orbit_####.exr``, ``<out>/png/orbit_####.png`` (``exr_pruned``,
``png_pruned``), ``--strip`` (default
``docs/orbit_demo.png``) and ``--table`` (default: the strip's name with ``.md``). The
last line printed is ``RESULT {json}``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
sys.path.insert(0, str(REPO_ROOT / "scripts"))

COVERED = 0.5        # alpha above which a pixel counts as covered (issue 14's coverage)
BLACK = 4.0 / 255.0  # a PNG pixel whose every channel is below this reads as black
MAGENTA = (1.0, 0.0, 1.0)


def parse_args(argv=None):
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", default=str(REPO_ROOT / "runs" / "demo"), help="run folder (default runs/demo)")
    p.add_argument("--capture", default=None, help="capture folder (default: the one run.json names)")
    p.add_argument("--out", default=str(Path(tempfile.gettempdir()) / "bt4d_orbit_strip"),
                   help="folder for the rendered frames")
    p.add_argument("--strip", default=str(REPO_ROOT / "docs" / "orbit_demo.png"), help="strip image (PNG)")
    p.add_argument("--table", default=None, help="coverage table (Markdown; default: --strip with .md)")
    p.add_argument("--degrees", type=float, default=30.0, help="azimuth range: -degrees .. +degrees")
    p.add_argument("--frames", type=int, default=13, help="frames along the arc (default 13: 5 degree steps)")
    p.add_argument("--label-step", type=float, default=10.0, help="strip: one frame every this many degrees")
    p.add_argument("--time", choices=("sweep", "freeze"), default="sweep",
                   help="Capture Time over the arc: the whole capture (sweep) or held at its middle (freeze)")
    p.add_argument("--prune-unobserved", action="store_true",
                   help="also render with render_path's Drop Unobserved Gaussians (two more strip rows and columns)")
    p.add_argument("--resolution-percentage", type=int, default=100)
    p.add_argument("--samples", type=int, default=0, help="load_result time samples (0: automatic)")
    return p.parse_args(argv)


# ----------------------------------------------------------------------------- geometry (no bpy)

def closest_point_of_axes(c0, d0, c1, d1) -> np.ndarray | None:
    """Midpoint of the shortest segment between the lines ``c0 + s d0`` and ``c1 + u d1``
    (both in front of their cameras: s, u > 0); None for (near) parallel axes."""
    c0, d0, c1, d1 = (np.asarray(v, np.float64) for v in (c0, d0, c1, d1))
    d0, d1 = d0 / np.linalg.norm(d0), d1 / np.linalg.norm(d1)
    b = float(d0 @ d1)
    den = 1.0 - b * b
    if den < 1e-8:
        return None
    w = c0 - c1
    s = (b * float(d1 @ w) - float(d0 @ w)) / den
    u = (float(d1 @ w) - b * float(d0 @ w)) / den
    if s <= 0 or u <= 0:
        return None
    return 0.5 * ((c0 + s * d0) + (c1 + u * d1))


def pair_centre_of_interest(c2w_a, c2w_b, fallback_depth: float | None = None) -> np.ndarray:
    """The point a stereo pair looks at: where its optical axes (OpenGL: -Z) come closest;
    for parallel axes, ``fallback_depth`` along the mean axis from the pair's middle."""
    a, b = np.asarray(c2w_a, np.float64), np.asarray(c2w_b, np.float64)
    p = closest_point_of_axes(a[:3, 3], -a[:3, 2], b[:3, 3], -b[:3, 2])
    if p is not None:
        return p
    if fallback_depth is None:
        raise ValueError("the pair's optical axes are parallel: give a depth to look at")
    fwd = -(a[:3, 2] + b[:3, 2])
    return 0.5 * (a[:3, 3] + b[:3, 3]) + fallback_depth * fwd / np.linalg.norm(fwd)


def arc_poses(centre, eye0, degrees: float, n: int, up=(0.0, 0.0, 1.0)) -> list[tuple[float, np.ndarray]]:
    """(azimuth in degrees, OpenGL c2w) for ``n`` cameras from ``-degrees`` to ``+degrees``
    about ``up`` through ``centre``, starting from ``eye0`` rotated, looking at ``centre``:
    constant distance and height. Positive azimuth turns counter-clockwise seen from above
    (with Z up: a camera looking at ``centre`` moves to its right)."""
    from engine.cameras import look_at_c2w

    centre, eye0, up = (np.asarray(v, np.float64) for v in (centre, eye0, up))
    up = up / np.linalg.norm(up)
    off = eye0 - centre
    out = []
    for az in np.linspace(-degrees, degrees, n) if n > 1 else [0.0]:
        a = math.radians(float(az))
        # Rodrigues: rotate the offset about ``up`` by ``a``
        rot = off * math.cos(a) + np.cross(up, off) * math.sin(a) + up * (up @ off) * (1 - math.cos(a))
        out.append((float(az), look_at_c2w(centre + rot, centre, up=tuple(up))))
    return out


# ----------------------------------------------------------------------------- Blender side

def train_rgb_cameras(scene) -> list:
    """The capture's RGB train cameras (imported by bt4d.import_capture), by name."""
    cams = [o for o in scene.objects if o.type == "CAMERA" and o.get("bt4d_role") == "train"
            and not o.get("bt4d_spike_file")]
    return sorted(cams, key=lambda o: o.name)


def key_arc_camera(scene, poses, ref_camera=None, name: str = "BT4D Arc"):
    """A camera (lens of ``ref_camera``) keyed at each pose on consecutive frames from
    ``scene.frame_start`` (linear between keys), made the scene camera."""
    import bpy
    from bpy_extras import anim_utils
    from mathutils import Matrix

    data = ref_camera.data.copy() if ref_camera is not None else bpy.data.cameras.new(name)
    data.name = name
    cam = bpy.data.objects.new(name, data)
    scene.collection.objects.link(cam)
    cam.rotation_mode = "XYZ"
    prev = None
    for i, (_, c2w) in enumerate(poses):
        m = Matrix([[float(v) for v in row] for row in c2w])
        cam.location = m.to_translation()
        eul = m.to_euler("XYZ", prev) if prev is not None else m.to_euler("XYZ")
        cam.rotation_euler = eul
        prev = eul.copy()
        f = scene.frame_start + i
        cam.keyframe_insert("location", frame=f)
        cam.keyframe_insert("rotation_euler", frame=f)
    ad = cam.animation_data
    for fc in anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot).fcurves:
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"
    scene.camera = cam
    return cam


def addon_module(sub: str):
    from importlib import import_module

    name = next(m for m in sys.modules if m.endswith(f"bullettime4d.{sub}"))
    return import_module(name)


def setup_orbit(scene, run_dir: str, capture: str, *, degrees: float, frames: int, time_mode: str,
                samples: int = 0):
    """Import the capture, load the run, key the arc camera and Capture Time. Returns
    (result object, arc camera, poses [(azimuth, c2w)], capture times per frame, centre)."""
    import bpy

    if bpy.ops.bt4d.import_capture(directory=str(capture)) != {"FINISHED"}:
        raise RuntimeError(f"could not import the capture {capture}")
    if bpy.ops.bt4d.load_result(directory=str(run_dir), num_samples=samples, key_time=False) != {"FINISHED"}:
        raise RuntimeError(f"could not load the run {run_dir}")
    gn = addon_module("bt4d_addon.gaussian_nodes")
    obj = gn.find_result_objects(scene)[0]
    pair = train_rgb_cameras(scene)
    if len(pair) < 2:
        raise SystemExit(f"{capture}: the orbit needs the stereo pair, found RGB train cameras "
                         f"{[o.name for o in pair]}")
    a, b = (np.array(o.matrix_world, np.float64) for o in pair[:2])
    eye0 = 0.5 * (a[:3, 3] + b[:3, 3])
    # parallel axes: look as deep as the reconstruction's robust centre lies along them
    fwd = -(a[:3, 2] + b[:3, 2]) / np.linalg.norm(a[:3, 2] + b[:3, 2])
    t0, t1 = (float(x) for x in obj["bt4d_time_range"])
    recon_centre, _ = addon_module("operators.bullet_time").result_centre_and_radius(obj, 0.5 * (t0 + t1))
    centre = pair_centre_of_interest(a, b, fallback_depth=max(float((recon_centre - eye0) @ fwd), 1e-3))
    poses = arc_poses(centre, eye0, degrees, frames)
    scene.frame_start, scene.frame_end = 1, len(poses)
    cam = key_arc_camera(scene, poses, ref_camera=pair[0])
    if time_mode == "sweep":
        gn.key_capture_time(obj, [(scene.frame_start, t0), (scene.frame_end, t1)])
    else:
        mid = 0.5 * (t0 + t1)
        gn.key_capture_time(obj, [(scene.frame_start, mid), (scene.frame_end, mid)], interpolation="CONSTANT")
    times = [gn.capture_time_at(obj, f) for f in range(scene.frame_start, scene.frame_end + 1)]
    return obj, cam, poses, times, centre


def render_both(scene, out: Path, resolution_percentage: int = 100, *, prune_unobserved: bool = False,
                tag: str = "") -> tuple[list[Path], list[Path]]:
    """The keyed path through bt4d.render_path: raw EXR, then opaque (hole-filled) PNG, into
    ``out/exr<tag>`` and ``out/png<tag>``."""
    import bpy

    scene.render.resolution_percentage = resolution_percentage
    scene.render.filepath = str(out / f"exr{tag}" / "orbit_####")
    if bpy.ops.bt4d.render_path(file_format="OPEN_EXR", load_back=False,
                                prune_unobserved=prune_unobserved) != {"FINISHED"}:
        raise RuntimeError("bt4d.render_path (EXR) did not finish")
    scene.render.film_transparent = False  # opaque PNG: the operator fills the holes
    scene.render.filepath = str(out / f"png{tag}" / "orbit_####")
    if bpy.ops.bt4d.render_path(file_format="PNG", load_back=False,
                                prune_unobserved=prune_unobserved) != {"FINISHED"}:
        raise RuntimeError("bt4d.render_path (PNG) did not finish")
    frames = range(scene.frame_start, scene.frame_end + 1)
    exr = [out / f"exr{tag}" / f"orbit_{f:04d}.exr" for f in frames]
    png = [out / f"png{tag}" / f"orbit_{f:04d}.png" for f in frames]
    missing = [str(p) for p in exr + png if not p.exists()]
    if missing:
        raise RuntimeError(f"render_path did not write {missing}")
    return exr, png


# ----------------------------------------------------------------------------- strip and table (no bpy)

def frame_stats(exr_path, png_path) -> dict:
    """coverage (alpha > 0.5 in the raw EXR), holes (the rest), black (PNG pixels whose every
    channel is below 4/255) and black_in_holes (black PNG pixels among the holes)."""
    from engine.io.images import read_exr_channels, read_image_rgba

    alpha = read_exr_channels(exr_path)["A"]
    png = read_image_rgba(png_path)[..., :3]
    black = np.all(png < BLACK, axis=-1)
    holes = alpha <= COVERED
    return {"coverage": float(np.mean(~holes)), "holes": float(np.mean(holes)), "black": float(np.mean(black)),
            "black_in_holes": float(np.mean(black[holes])) if holes.any() else 0.0}


def coverage_table(rows: list[dict], variants: tuple[str, ...] = ("",)) -> str:
    """Markdown: per frame, for each variant (key suffix; "" = the default render and e.g.
    "_pruned"): coverage (alpha > 0.5, raw), holes before filling, black pixels in the PNG."""
    names = {"": "", "_pruned": " (unobserved dropped)"}
    head = ["frame", "azimuth", "capture time"]
    for v in variants:
        n = names.get(v, v)
        head += [f"coverage{n}", f"holes before filling{n}", f"black in PNG{n}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["frame"]), f"{r['azimuth']:+.0f}°", f"{r['time']:.3f} s"]
        for v in variants:
            cells += [f"{100 * r['coverage' + v]:.1f} %", f"{100 * r['holes' + v]:.1f} %",
                      f"{100 * r['black' + v]:.2f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def raw_over(exr_path, colour=MAGENTA) -> np.ndarray:
    """sRGB [H,W,3] of the raw premultiplied EXR composited over ``colour``."""
    from engine.colour import linear_to_srgb
    from engine.io.images import read_exr_channels

    c = read_exr_channels(exr_path)
    lin = np.stack([c["R"], c["G"], c["B"]], -1) + (1.0 - c["A"][..., None]) * np.asarray(colour, np.float32)
    return np.clip(linear_to_srgb(np.clip(lin, 0, 1)), 0, 1)


def pick_labelled(azimuths, step: float) -> list[int]:
    """Indices of the frames whose azimuth is a multiple of ``step`` (nearest frame each)."""
    az = np.asarray(azimuths, np.float64)
    lo, hi = math.ceil(az.min() / step - 1e-6), math.floor(az.max() / step + 1e-6)
    picks = [int(np.argmin(np.abs(az - k * step))) for k in range(lo, hi + 1)]
    return sorted(set(picks)) or list(range(len(az)))


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def montage(rows: list[list[np.ndarray]], labels: list[str], caption: str, path, *, colours: int = 256) -> Path:
    """Tiles in columns (one list per row), a label above each column, a caption line;
    saved as a ``colours``-colour palette PNG (small enough for a README)."""
    from PIL import Image, ImageDraw

    from engine.io.fileio import atomic_path

    h, w = rows[0][0].shape[:2]
    gap, band, cap = 2, 14, 14
    cols = len(rows[0])
    W = cols * w + (cols - 1) * gap
    H = cap + band + len(rows) * h + (len(rows) - 1) * gap
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    draw.text((2, 1), caption, fill=(0, 0, 0), font=_font(10))
    for i, label in enumerate(labels):
        draw.text((i * (w + gap) + 2, cap + 1), label, fill=(0, 0, 0), font=_font(11))
    for j, row in enumerate(rows):
        for i, img in enumerate(row):
            tile = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
            canvas.paste(tile, (i * (w + gap), cap + band + j * (h + gap)))
    if colours and colours < 256 ** 3:
        # octree keeps the small saturated regions (the checker cube) that median cut merged
        canvas = canvas.quantize(colors=int(colours), method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    path = Path(path)
    with atomic_path(path, ".png") as tmp:
        canvas.save(tmp, format="PNG", optimize=True)
    return path


def main(argv=None) -> int:
    args = parse_args(argv)
    import bpy
    from headless_example import ensure_addon

    from engine.io.images import read_image_rgba

    t_start = time.monotonic()
    run_dir = Path(args.run).resolve()
    if not (run_dir / "checkpoint.pt").exists():
        print(f"error: {run_dir} holds no checkpoint.pt (train it first: make demo)", file=sys.stderr)
        return 1
    capture = args.capture
    if capture is None:
        capture = json.loads((run_dir / "run.json").read_text()).get("capture")
        if not capture:
            print(f"error: {run_dir / 'run.json'} names no capture: pass --capture", file=sys.stderr)
            return 1
    out = Path(args.out).resolve()
    strip = Path(args.strip).resolve()
    table_path = Path(args.table).resolve() if args.table else strip.with_suffix(".md")

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    ensure_addon()
    scene = bpy.context.scene
    obj, cam, poses, times, centre = setup_orbit(scene, str(run_dir), capture, degrees=args.degrees,
                                                 frames=args.frames, time_mode=args.time, samples=args.samples)
    variants = {"": render_both(scene, out, args.resolution_percentage)}
    if args.prune_unobserved:
        variants["_pruned"] = render_both(scene, out, args.resolution_percentage, prune_unobserved=True,
                                          tag="_pruned")

    rows = []
    for i, ((az, _), t) in enumerate(zip(poses, times)):
        row = {"frame": scene.frame_start + i, "azimuth": az, "time": t}
        for tag, (exr, png) in variants.items():
            row.update({k + tag: v for k, v in frame_stats(exr[i], png[i]).items()})
        rows.append(row)
        print(f"frame {row['frame']:3d}  azimuth {az:+6.1f}°  t={t:.4f} s  " + "  ".join(
            f"[{tag or 'default'}] coverage {100 * row['coverage' + tag]:5.1f} %  black in PNG "
            f"{100 * row['black' + tag]:.2f} %" for tag in variants), flush=True)
    table = coverage_table(rows, tuple(variants))
    from engine.io.fileio import atomic_write

    atomic_write(table_path, lambda fh: fh.write(table.encode()), fsync=False)
    print(table, end="")

    picks = pick_labelled([p[0] for p in poses], args.label_step)
    labels = [f"{poses[i][0]:+.0f}°  t={times[i]:.3f}s" for i in picks]
    strip_rows, names = [], []
    for tag, (exr, png) in variants.items():
        strip_rows.append([read_image_rgba(png[i])[..., :3] for i in picks])
        strip_rows.append([raw_over(exr[i]) for i in picks])
        names.append("PNG, raw" + (" | unobserved dropped: PNG, raw" if tag else ""))
    caption = (f"{run_dir.name}: orbit ±{args.degrees:g}° (bt4d.render_path). Rows: opaque PNG (holes filled), "
               f"raw render (uncovered = magenta)" + ("; then the same with unobserved Gaussians dropped"
                                                       if args.prune_unobserved else ""))
    montage(strip_rows, labels, caption, strip)
    exr, png = variants[""]
    summary = {"run": str(run_dir), "capture": str(capture), "centre": [float(c) for c in centre],
               "camera": cam.name, "frames": len(poses), "strip": str(strip),
               "strip_kb": round(strip.stat().st_size / 1024, 1),
               "table": str(table_path), "exr": [str(p) for p in exr], "png": [str(p) for p in png],
               "min_coverage": min(r["coverage"] for r in rows), "max_black": max(r["black"] for r in rows),
               "seconds": round(time.monotonic() - t_start, 1)}
    print("RESULT " + json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
