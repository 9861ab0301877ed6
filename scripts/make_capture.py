#!/usr/bin/env python
"""Render a synthetic hybrid capture (stereo RGB + spike camera + eval camera) with Cycles.

Run with the project's Python (``bpy`` is the Blender module)::

    .venv/bin/python scripts/make_capture.py --out demo_capture
    .venv/bin/python scripts/make_capture.py --out big_capture --preset large

Scenes, lit by a sharp sun plus an even sky: ``classic`` (presets demo, large, fast;
``capture_classic.py``): brick wall, checker floor, a spinning cube, a swinging striped
ball, a bobbing torus; ``novel`` (``--preset novel``, ``capture_novel.py``): the table-top
novel-view benchmark (weakly-textured floor, textured wall, thin parts, a fast ball, a
turntable with letters) with eval cameras 10-30 deg off the pair (``--eval-angles``);
``random`` (``--preset random --seed N``, ``capture_random.py``): a new set, rig (0.8-3 m,
baselines 0.08-0.35 m), objects, motion, light, camera sizes and sensor noise for every seed;
``random_between`` (``--preset random_between --seed N``): the same draw with bounces and
vibrations added, motion 30 FPS cannot sample (what the spike camera is for).

Ground truth (``capture_truth.py``): ``--depth`` writes planar depth for every rendered
view (``depth_file_path``); every capture gets ``ground_truth.objects`` (each moving
object's object-to-world matrix at the light rate and surface samples).

Rig (CAPTURE_FORMAT.md): ``rgb0``/``rgb1`` stereo pair (30 FPS, baseline ~11 % of the
distance to the subject), ``spike0`` co-located with ``rgb0`` (same pose and field of
view, lower resolution, 20 kHz), ``eval0`` held out, above and between the pair, at
``--eval-fps``. RGB/eval frames are 8-bit sRGB PNGs rendered with the Standard view
transform (plain sRGB encoding, no tone curve). The spike stream is simulated from
linear light rendered at the spike resolution at ``--light-hz``:
``engine.spike.simulate.simulate_spikes`` interpolates it in time to 20 kHz, with a per-pixel
gain map and a little dark current; linear white (1.0) fires every ``1/light_scale``
frames. No ``points.ply`` is written unless ``--points``, so by default the engine's stereo
initialisation is exercised.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for _p in (REPO, REPO / "scripts"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import bpy  # noqa: E402
import capture_between  # noqa: E402
import capture_classic  # noqa: E402
import capture_novel  # noqa: E402
import capture_random  # noqa: E402
import capture_truth  # noqa: E402

from bt4d_addon import blender_cameras  # noqa: E402
from engine.cameras import Intrinsics, look_at_c2w  # noqa: E402
from engine.io.images import write_exr  # noqa: E402

PRESETS = {
    # ~0.2 s, shipped with the add-on (<= 6 MB)
    "demo": dict(seconds=0.2, rgb_size=(160, 120), spike_size=(80, 60), eval_fps=300.0,
                 samples=16, light_hz=1000.0),
    # a heavier benchmark-like capture
    "large": dict(seconds=0.5, rgb_size=(320, 240), spike_size=(160, 120), eval_fps=300.0,
                  samples=32, light_hz=2000.0),
    # issue 43: the paper's rig at its real size -- RGB 1080x720 (train and eval cameras), a
    # Vidar-shaped 400x250 spike camera of its own lens (square pixels, the RGB horizontal field of
    # view), 0.5 s at 20 kHz with the sensor noise below; for benchmarks (tools time-to-result), never
    # the unit tests
    "real": dict(seconds=0.5, rgb_size=(1080, 720), spike_size=(400, 250), eval_fps=60.0,
                 samples=16, light_hz=1000.0),
    # fast motion (3x the demo's speeds: about 1 rad of swing phase and 2.5 rad of cube spin per
    # RGB frame), longer and larger than the demo: the spike-guidance benchmark scene
    "fast": dict(seconds=0.3, rgb_size=(192, 144), spike_size=(96, 72), eval_fps=300.0,
                 samples=16, light_hz=2000.0, speed=3.0),
    # the novel-view benchmark (issue 14): table-top rig (pair 0.2 m apart ~1 m away), weakly
    # textured floor, textured wall, thin parts, a fast ball, a turntable with letters; eval
    # cameras 10-30 deg off the pair (to the side and above) and ground-truth depth everywhere
    "novel": dict(seconds=0.2, rgb_size=(160, 120), spike_size=(80, 60), eval_fps=120.0,
                  samples=16, light_hz=1000.0, scene="novel",
                  eval_angles="side10,side20,side30,up10,up20,up30", extra_eval_fps=60.0, depth=True),
    # issue 11: the novel set with motion 30 FPS cannot sample (bounces, 15 Hz vibrations that
    # are back at rest at every RGB instant): only the spike stream sees it
    "between": dict(seconds=0.2, rgb_size=(160, 120), spike_size=(80, 60), eval_fps=120.0,
                    samples=16, light_hz=1000.0, scene="between",
                    eval_angles="side20,up20", extra_eval_fps=120.0, depth=True),
    # a new set, rig, motion, light, camera sizes and sensor noise for every --seed (capture_random.py):
    # the scenes to judge a change on that nobody tuned on
    "random": dict(seconds=0.3, eval_fps=120.0, samples=16, light_hz=1000.0, scene="random",
                   eval_angles="side20,up20", extra_eval_fps=60.0, depth=True),
    # the same draw with motion 30 FPS cannot sample added (bounces, vibrations; capture_random.py):
    # random scenes on which a spike camera can pay between the RGB instants (issue 47)
    "random_between": dict(seconds=0.3, eval_fps=120.0, samples=16, light_hz=1000.0, scene="random",
                           motion="between", eval_angles="side20,up20", extra_eval_fps=60.0, depth=True),
}
# keys that do not change the spike light (kept out of the --light-cache key)
_NOT_LIGHT = ("eval_angles", "extra_eval_fps", "depth", "gain_std", "dark_current", "photons_per_threshold")
GT_POINTS = 2000  # surface samples per moving object in ground_truth/objects.npz
# scene name -> its module
SCENES = {"classic": capture_classic, "novel": capture_novel, "between": capture_between, "random": capture_random}
RGB_FPS = 30.0
SPIKE_HZ = 20000.0
HFOV_DEG = 54.0
# spike model defaults (recorded in transforms.json under spike_streams[i]["sim"])
LIGHT_SCALE = 1.0 / 3.0   # light per spike frame for linear luminance 1.0: white fires every 3rd frame
GAIN_STD = 0.03
DARK_CURRENT = 0.002
PHOTONS_PER_THRESHOLD = 1000.0  # Poisson shot noise on each frame's charge


# ----------------------------------------------------------------------------- motion

# ----------------------------------------------------------------------------- scene

def _material(name: str, build) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 creates materials without nodes
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Roughness"].default_value = 0.0
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    colour = build(nt)
    nt.links.new(colour, bsdf.inputs["Color"])
    return mat


def _mix(nt, a, b, fac, blend="MIX"):
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = blend
    if isinstance(fac, float):
        mix.inputs[0].default_value = fac
    else:
        nt.links.new(fac, mix.inputs[0])
    nt.links.new(a, mix.inputs[6])
    nt.links.new(b, mix.inputs[7])
    return mix.outputs[2]


def build_scene(samples: int, seed: int, scene_name: str = "classic") -> tuple[bpy.types.Scene, dict]:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = samples
    cy.use_adaptive_sampling = False
    cy.seed = seed
    cy.use_animated_seed = False
    cy.max_bounces = 3
    cy.diffuse_bounces = 1
    cy.glossy_bounces = 0
    cy.transmission_bounces = 0
    cy.transparent_max_bounces = 0
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    try:
        import _cycles
        have_oidn = bool(getattr(_cycles, "with_openimagedenoise", False))
    except ImportError:
        have_oidn = False
    cy.use_denoising = have_oidn
    if have_oidn:
        cy.denoiser = "OPENIMAGEDENOISE"
    scene.render.use_persistent_data = True
    scene.render.use_motion_blur = False
    scene.render.film_transparent = False
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    scene.display_settings.display_device = "sRGB"

    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.8, 0.85, 1.0, 1)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.45
    scene.world = world
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.6
    sun.data.angle = 0.0
    sun.rotation_euler = (math.radians(40), math.radians(-20), math.radians(-25))
    scene.collection.objects.link(sun)

    return scene, SCENES[scene_name].build_objects(scene, _material, _mix)


def object_poses(t: float, speed: float = 1.0, scene_name: str = "classic"):
    return SCENES[scene_name].object_poses(t, speed)


def set_time(objs: dict, t: float, speed: float = 1.0, scene_name: str = "classic") -> None:
    for name, (loc, rot) in object_poses(t, speed, scene_name).items():
        objs[name].location = loc
        objs[name].rotation_euler = rot


def orbit_eye(eye, target, side_deg: float = 0.0, up_deg: float = 0.0) -> tuple:
    """``eye`` moved on the sphere around ``target``: ``side_deg`` of azimuth about the vertical
    through the target (positive: to the pair's left, -X, for a pair looking along +Y) and
    ``up_deg`` of elevation; same distance. At the novel rig's ~13 deg downward view, 20 deg
    of azimuth is 19.5 deg of arc from the pair; elevation is exact."""
    v = np.asarray(eye, np.float64) - np.asarray(target, np.float64)
    r = np.linalg.norm(v)
    az = math.atan2(v[1], v[0]) - math.radians(side_deg)
    el = math.asin(v[2] / r) + math.radians(up_deg)
    return tuple(np.asarray(target) + r * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                     math.sin(el)]))


def eval_angles(spec: str | None) -> dict[str, tuple[float, float]]:
    """'side10,up20,...' -> {'eval_side10': (10, 0), 'eval_up20': (0, 20), ...} (degrees)."""
    out = {}
    for item in filter(None, (spec or "").replace(" ", "").split(",")):
        for kind in ("side", "up"):
            if item.startswith(kind):
                try:
                    deg = float(item[len(kind):])
                except ValueError:
                    break
                out[f"eval_{item}"] = (deg, 0.0) if kind == "side" else (0.0, deg)
                break
        else:
            raise ValueError(f"--eval-angles: {item!r} is not side<deg> or up<deg>")
    return out


def rig(rgb_size, spike_size, scene, scene_name: str = "classic", angles: dict | None = None) -> dict:
    """name -> dict(intr, c2w, role, blender object). ``angles``: extra eval camera name ->
    (side, up) degrees off the stereo pair's midpoint, around the target."""
    w, h = rgb_size
    f = (w / 2.0) / math.tan(math.radians(HFOV_DEG) / 2.0)
    rgb_intr = Intrinsics(w, h, f, f, w / 2.0, h / 2.0)
    target, eyes = SCENES[scene_name].TARGET, dict(SCENES[scene_name].CAMERA_EYES)
    mid = 0.5 * (np.asarray(eyes["rgb0"]) + np.asarray(eyes["rgb1"]))
    eval0 = getattr(SCENES[scene_name], "EVAL0_ANGLES", None)  # (side, up) deg off the pair
    if eval0 is not None:
        eyes["eval0"] = orbit_eye(mid, target, *eval0)
    for name, (side, up) in (angles or {}).items():
        eyes[name] = orbit_eye(mid, target, side, up)
    cams = {}
    for name in eyes:
        cams[name] = dict(intr=rgb_intr, c2w=look_at_c2w(eyes[name], target),
                          role="eval" if name.startswith("eval") else "train")
    spike_intr = rgb_intr.scaled(*spike_size)
    sw, sh = spike_size
    if abs(sw * h - sh * w) > 0:
        # a sensor of another shape (a Vidar camera is 400x250 beside a 4:3 or 3:2 RGB camera): a camera of
        # its own, square pixels, the RGB lens's horizontal field of view (engine.spike.render.view_warp)
        fs = f * sw / w
        spike_intr = Intrinsics(sw, sh, fs, fs, sw / 2.0, sh / 2.0)
    cams["spike0"] = dict(intr=spike_intr, c2w=cams["rgb0"]["c2w"].copy(), role="train")
    for name, cam in cams.items():
        cam["object"] = blender_cameras.create_camera_object(name, cam["intr"], cam["c2w"], scene.collection)
    return cams


# ----------------------------------------------------------------------------- render

def render_to(scene, cam: dict, path: Path, fmt: str) -> None:
    scene.camera = cam["object"]
    blender_cameras.configure_render(scene, cam["intr"])
    st = scene.render.image_settings
    if fmt == "PNG":
        st.file_format = "PNG"
        st.color_mode = "RGB"
        st.color_depth = "8"
        st.compression = 90
    else:
        st.file_format = "OPEN_EXR"
        st.color_mode = "RGB"
        st.color_depth = "32"
        st.exr_codec = "ZIP"
    scene.render.filepath = str(path)
    scene.render.use_file_extension = False
    bpy.ops.render.render(write_still=True)
    if not path.exists():
        raise RuntimeError(f"Cycles did not write {path}")


def stereo_pointmap(scene, cams: dict, out: Path, names=("rgb0", "rgb1"),
                    stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The scene points seen by each pixel (every ``stride``-th) of the stereo pair at the
    current time, coloured from that camera's rendered frame 0: what a dense two-view
    pointmap (DUSt3R, which the paper uses and we cannot run offline) estimates, here exact.
    Pixel rays follow the OpenCV pinhole model of ``engine.cameras`` (x right, y down, z forward)."""
    from engine.io.images import read_image

    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    xyz, rgb = [], []
    for name in names:
        cam = cams[name]
        k, c2w = cam["intr"], np.asarray(cam["c2w"], dtype=np.float64)  # OpenGL camera-to-world
        img = read_image(out / f"rgb/{name}/000000.png")[..., :3]
        origin = c2w[:3, 3]
        for v in range(stride // 2, k.height, stride):
            for u in range(stride // 2, k.width, stride):
                d_cv = np.array([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, 1.0])
                d = c2w[:3, :3] @ (d_cv * np.array([1.0, -1.0, -1.0]))  # OpenCV -> OpenGL camera axes
                hit, loc, *_ = scene.ray_cast(depsgraph, origin.tolist(), (d / np.linalg.norm(d)).tolist())
                if hit:
                    xyz.append(tuple(loc))
                    rgb.append(img[v, u])
    return np.asarray(xyz, np.float32), np.clip(np.asarray(rgb, np.float32), 0.0, 1.0)


def frame_times(seconds: float, fps: float) -> np.ndarray:
    n = int(math.floor(seconds * fps + 1e-6)) + 1
    return np.arange(n) / fps


def render_light(scene, objs, cam, times, work: Path, log, speed: float = 1.0,
                 scene_name: str = "classic") -> np.ndarray:
    """Linear Rec.709 luminance at the spike camera for each time: (T, H, W) float32."""
    from engine.colour import luminance
    from engine.io.images import read_image

    out = np.empty((len(times), cam["intr"].height, cam["intr"].width), np.float32)
    for i, t in enumerate(times):
        set_time(objs, float(t), speed, scene_name)
        p = work / f"light_{i:06d}.exr"
        render_to(scene, cam, p, "EXR")
        out[i] = luminance(read_image(p)[..., :3])
        p.unlink()
        if i % 50 == 0:
            log(f"  light {i + 1}/{len(times)}")
    return out


def write_pointmap(scene, objs, cams, out: Path, cfg: dict) -> Path:
    from engine.io.points import write_points

    set_time(objs, 0.0, cfg["speed"], cfg.get("scene", "classic"))
    xyz, rgb = stereo_pointmap(scene, cams, out)
    path = write_points(out / "points.ply", xyz, rgb)
    print(f"points: {len(xyz)} from the rgb0/rgb1 pointmap at t=0 -> {path}", flush=True)
    return path


def write_object_truth(scene, objs, times, out: Path, cfg: dict, seed: int) -> dict:
    """ground_truth/objects.npz (times, per object [T,4,4] object-to-world and [P,3] surface
    samples in object space) and its transforms.json block."""
    from engine.io.fileio import atomic_path

    mats = capture_truth.object_matrices(
        objs, times, lambda t: set_time(objs, t, cfg["speed"], cfg.get("scene", "classic")))
    arrays = {"times": np.asarray(times, np.float64)}
    for k, (name, obj) in enumerate(sorted(objs.items())):
        arrays[name] = mats[name]
        arrays[f"{name}_points"] = capture_truth.surface_samples(obj, GT_POINTS, seed + 10 + k)
    path = out / "ground_truth" / "objects.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, ".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return {"objects": {"file_path": "ground_truth/objects.npz", "rate_hz": float(cfg["light_hz"]),
                        "t0": float(times[0]), "names": sorted(objs)}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="capture folder to write")
    ap.add_argument("--preset", choices=sorted(PRESETS), default="demo")
    ap.add_argument("--seconds", type=float)
    ap.add_argument("--rgb-size", help="WxH of the RGB and eval cameras, e.g. 160x120")
    ap.add_argument("--spike-size", help="WxH of the spike camera, e.g. 80x60 (the RGB shape: the same field of "
                                         "view); another shape, e.g. 400x250 as a Vidar camera, is a camera of "
                                         "its own: square pixels, the RGB lens's horizontal field of view")
    ap.add_argument("--eval-fps", type=float)
    ap.add_argument("--light-hz", type=float, help="rate at which linear light is rendered for the spike simulation")
    ap.add_argument("--samples", type=int, help="Cycles samples per pixel")
    ap.add_argument("--speed", type=float, help="motion speed multiplier (1: the demo's motion)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-angles", help="extra eval cameras off the stereo pair, e.g. side10,side20,up20 "
                                          "(degrees of azimuth to the pair's left / of elevation, around the target)")
    ap.add_argument("--extra-eval-fps", type=float, help="frame rate of the extra eval cameras (default 60: "
                                                         "every RGB instant and the midpoint between two)")
    ap.add_argument("--depth", action=argparse.BooleanOptionalAction, default=None,
                    help="write ground-truth planar depth (EXR, depth_file_path) for every rendered view")
    ap.add_argument("--light-cache", type=Path, help="npz to reuse / store the rendered spike light")
    ap.add_argument("--points", action="store_true",
                    help="also write points.ply: the stereo pair's exact pointmap at t=0 (a perfect DUSt3R stand-in)")
    ap.add_argument("--points-only", action="store_true",
                    help="only (re)write points.ply into an existing capture made with the same options")
    args = ap.parse_args(argv)

    cfg = dict(PRESETS[args.preset])
    if cfg.get("scene") == "random":  # the seed draws the scene, its camera sizes and its sensor noise
        cfg.update(capture_random.configure(args.seed, cfg.get("motion", "smooth")))
    cfg.setdefault("gain_std", GAIN_STD)
    cfg.setdefault("dark_current", DARK_CURRENT)
    cfg.setdefault("photons_per_threshold", PHOTONS_PER_THRESHOLD)
    cfg.setdefault("speed", 1.0)
    cfg.setdefault("extra_eval_fps", 60.0)
    cfg.setdefault("depth", False)
    for key in ("seconds", "eval_fps", "light_hz", "samples", "speed", "eval_angles", "extra_eval_fps", "depth"):
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)
    for key in ("rgb_size", "spike_size"):
        if getattr(args, key):
            w, h = getattr(args, key).lower().split("x")
            cfg[key] = (int(w), int(h))
    if cfg["seconds"] <= 0:
        ap.error("--seconds must be > 0")
    if cfg["speed"] <= 0:
        ap.error("--speed must be > 0")
    if (cfg["spike_size"][0] * cfg["spike_size"][1]) % 8:
        ap.error("--spike-size: width * height must be a multiple of 8 (Vidar frames are whole bytes)")

    try:
        angles = eval_angles(cfg.get("eval_angles"))
    except ValueError as exc:
        ap.error(str(exc))
    scene_name = cfg.get("scene", "classic")
    out: Path = args.out.resolve()
    if args.points_only:
        if not (out / "rgb/rgb0/000000.png").exists():
            ap.error(f"--points-only: {out} has no rgb/rgb0/000000.png; generate the capture first")
        scene, objs = build_scene(cfg["samples"], args.seed, scene_name)
        cams = rig(cfg["rgb_size"], cfg["spike_size"], scene, scene_name)
        write_pointmap(scene, objs, cams, out, cfg)
        return 0
    if out.exists() and any(out.iterdir()) and not (out / "transforms.json").exists():
        ap.error(f"{out} exists, is not empty and is not a capture; refusing to overwrite")
    for sub in ("rgb", "eval", "spike", "depth", "ground_truth"):
        shutil.rmtree(out / sub, ignore_errors=True)
    (out / "transforms.json").unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)

    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:7.1f}s] {msg}", flush=True)

    scene, objs = build_scene(cfg["samples"], args.seed, scene_name)
    cams = rig(cfg["rgb_size"], cfg["spike_size"], scene, scene_name, angles)
    log(f"scene built: {cfg}")

    def record(cam_name, rel, t, i):
        rec = {"file_path": rel, "camera": cam_name, "time": round(float(t), 9),
               "transform_matrix": cams[cam_name]["c2w"].tolist()}
        if cfg["depth"]:
            drel = f"depth/{cam_name}/{i:06d}.exr"
            (out / drel).parent.mkdir(parents=True, exist_ok=True)
            write_exr(out / drel, {"Z": capture_truth.planar_depth(scene, cams[cam_name]["intr"],
                                                                   cams[cam_name]["c2w"])})
            rec["depth_file_path"] = drel
        return rec

    def pose(t):
        set_time(objs, float(t), cfg["speed"], scene_name)

    frames, eval_frames = [], []
    rgb_times = frame_times(cfg["seconds"], RGB_FPS)
    for i, t in enumerate(rgb_times):
        pose(t)
        for name in ("rgb0", "rgb1"):
            rel = f"rgb/{name}/{i:06d}.png"
            render_to(scene, cams[name], out / rel, "PNG")
            frames.append(record(name, rel, t, i))
    log(f"rgb: {len(rgb_times)} frames x 2 cameras")
    eval_sets = [("eval0", frame_times(cfg["seconds"], cfg["eval_fps"]))]
    eval_sets += [(name, frame_times(cfg["seconds"], cfg["extra_eval_fps"])) for name in angles]
    for name, times in eval_sets:
        for i, t in enumerate(times):
            pose(t)
            rel = f"eval/{name}/{i:06d}.png"
            render_to(scene, cams[name], out / rel, "PNG")
            eval_frames.append(record(name, rel, t, i))
        log(f"eval {name}: {len(times)} frames")

    n_spike = int(round(cfg["seconds"] * SPIKE_HZ))
    light_times = frame_times(cfg["seconds"], cfg["light_hz"])
    if light_times[-1] < (n_spike - 1) / SPIKE_HZ:
        light_times = np.append(light_times, light_times[-1] + 1.0 / cfg["light_hz"])
    spike_cam = cams["spike0"]
    key = {k: v for k, v in cfg.items() if k not in _NOT_LIGHT}
    key = dict(key, seed=args.seed, n=len(light_times))
    key = json.dumps({k: list(v) if isinstance(v, tuple) else v for k, v in key.items()}, sort_keys=True)
    light = None
    if args.light_cache and args.light_cache.exists():
        with np.load(args.light_cache) as z:
            if str(z["key"]) == key:
                light = z["light"]
                log(f"light: reused {args.light_cache}")
    if light is None:
        with tempfile.TemporaryDirectory(prefix="bt4d_light_") as work:
            light = render_light(scene, objs, spike_cam, light_times, Path(work), log, cfg["speed"], scene_name)
        if args.light_cache:
            np.savez_compressed(args.light_cache, light=light, key=np.array(key))
        log(f"light: {len(light_times)} frames at {cfg['light_hz']} Hz, "
            f"{spike_cam['intr'].width}x{spike_cam['intr'].height}")

    from engine.io.spikes import write_spikes
    from engine.spike.simulate import make_gain_map, simulate_spikes

    h, w = light.shape[1:]
    gain = make_gain_map(h, w, cfg["gain_std"], args.seed + 1)
    spikes = simulate_spikes(light * LIGHT_SCALE, rate_hz=SPIKE_HZ, num_frames=n_spike, t0=0.0,
                             light_times=light_times, threshold=1.0, gain=gain,
                             dark_current=cfg["dark_current"], shot_noise=True,
                             photons_per_threshold=cfg["photons_per_threshold"], seed=args.seed + 2)
    write_spikes(out / "spike" / "spike0.dat", spikes)
    log(f"spikes: {n_spike} frames at {SPIKE_HZ:.0f} Hz, mean rate {spikes.mean():.3f} per pixel-frame")

    def cam_record(name):
        k = cams[name]["intr"]
        return {"w": k.width, "h": k.height, "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
                "role": cams[name]["role"]}

    transforms = {
        "version": 1,
        "generator": {"script": "scripts/make_capture.py", "preset": args.preset, "seed": args.seed,
                      "samples": cfg["samples"], "light_hz": cfg["light_hz"], "speed": cfg["speed"],
                      "scene": scene_name, "eval_angles": {n: {"side_deg": a[0], "up_deg": a[1]}
                                                           for n, a in angles.items()}},
        "cameras": {name: cam_record(name) for name in cams},
        "frames": frames,
        "eval_frames": eval_frames,
        "spike_streams": [{
            "file_path": "spike/spike0.dat", "camera": "spike0", "rate_hz": SPIKE_HZ, "t0": 0.0,
            "num_frames": n_spike, "w": w, "h": h, "co_located_with": "rgb0",
            "transform_matrix": spike_cam["c2w"].tolist(),
            "sim": {"intensity": "rec709_luminance_linear", "light_scale": LIGHT_SCALE, "threshold": 1.0,
                    "gain_std": cfg["gain_std"], "dark_current": cfg["dark_current"],
                    "shot_noise": True, "photons_per_threshold": cfg["photons_per_threshold"]},
        }],
    }
    if scene_name == "random":  # what the seed drew, for the record
        transforms["generator"]["random"] = capture_random.PARAMS
    transforms["ground_truth"] = write_object_truth(scene, objs, light_times, out, cfg, args.seed)
    log(f"ground truth: {len(light_times)} object poses at {cfg['light_hz']} Hz for {sorted(objs)}")
    if args.points:
        write_pointmap(scene, objs, cams, out, cfg)
    (out / "transforms.json").write_text(json.dumps(transforms, indent=1))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    log(f"wrote {out} ({size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
