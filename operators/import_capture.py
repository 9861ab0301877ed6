"""``bpy.ops.bt4d.import_capture(directory=...)``: a capture folder -> Blender cameras.

Everything is loaded and validated first (``engine.io.capture.load_capture`` plus the image
headers) into a plain :class:`ImportPlan`; only then are datablocks created, so a bad
capture leaves the file untouched. Should building still fail, everything created so far
is removed again.

What the import creates, in a new collection named after the capture folder:

* one camera object per capture camera, named after it: lens, sensor and shift from the
  pinhole intrinsics (``bt4d_addon.blender_cameras``), ``matrix_world`` = the OpenGL
  camera-to-world of the camera's first frame (keyframed per frame time when it moves);
* custom properties ``bt4d_*`` on each object: role, intrinsics, frame count, first
  frame, and for spike cameras the stream file, rate, frame count, t0, size and the
  co-located RGB camera;
* the camera's frames as a background image sequence (visible when looking through it).

Time mapping: capture time ``t`` is scene frame ``frame_start + (t - t_start) * fps``.
``fps`` defaults to the main train camera's frame rate; the scene's resolution and pixel
aspect follow the main camera (the first train camera with RGB frames).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import bpy
from bpy.props import BoolProperty, IntProperty, StringProperty
from bpy.types import Operator

from ..bt4d_addon import blender_cameras, scene_build
from ..bt4d_addon.engine_bridge import CaptureError, load_capture, read_image_size

FRAME_START = 1
_NUM_RE = re.compile(r"^(.*?)(\d+)(\D*)$")


# ----------------------------------------------------------------------------- plan (no bpy data)

@dataclass
class SequencePlan:
    """A camera's frames as one Blender image sequence."""

    first_path: Path
    is_sequence: bool                   # False: a single still image (no number pattern)
    offsets: dict[int, int]             # scene frame -> image_user.frame_offset
    duration: int


@dataclass
class CameraPlan:
    name: str
    intrinsics: object                   # engine.cameras.Intrinsics
    role: str
    poses: list[tuple[float, object]]    # (time s, c2w 4x4) sorted by time; >= 1 entry
    moving: bool
    num_frames: int
    first_frame: Path | None
    stream: object | None = None         # engine.io.capture.SpikeStreamInfo
    sequence: SequencePlan | None = None
    pose_source: str = "frames"


@dataclass
class ImportPlan:
    root: Path
    name: str
    format: str
    cameras: list[CameraPlan]
    main_camera: str
    fps: int
    time_range: tuple[float, float]
    frame_start: int
    frame_end: int
    num_frames: int
    num_eval_frames: int
    streams: list = field(default_factory=list)

    def frame_of(self, t: float) -> float:
        return self.frame_start + (float(t) - self.time_range[0]) * self.fps


def _image_size(path: Path):
    try:
        return read_image_size(path)
    except ImportError:  # e.g. EXR without the OpenEXR module: Blender reads it later anyway
        return None


def _validate_images(frames) -> None:
    for fr in frames:
        size = _image_size(fr.path)
        k = fr.intrinsics
        if size is not None and k is not None and tuple(size) != (k.width, k.height):
            raise CaptureError(fr.path, f"image is {size[0]}x{size[1]} pixels but camera {fr.camera!r} "
                                        f"expects {k.width}x{k.height}")


def _sequence_plan(frames, plan_frame_of, frame_start: int, frame_end: int) -> SequencePlan:
    """Which file each scene frame shows: the frame nearest in time (earlier on ties)."""
    first = frames[0].path
    parsed = [_NUM_RE.match(f.path.stem) for f in frames]
    pattern_ok = all(m is not None for m in parsed) and all(
        f.path.parent == first.parent and f.path.suffix == first.suffix
        and m.group(1) == parsed[0].group(1) and m.group(3) == parsed[0].group(3)
        and len(m.group(2)) == len(parsed[0].group(2))
        for f, m in zip(frames, parsed))
    duration = frame_end - frame_start + 1
    if not pattern_ok:
        return SequencePlan(first, False, {}, duration)
    numbers = [int(m.group(2)) for m in parsed]
    key_frames = [plan_frame_of(f.time) for f in frames]
    offsets = {}
    j = 0
    for f in range(frame_start, frame_end + 1):
        while j + 1 < len(frames) and abs(key_frames[j + 1] - f) < abs(key_frames[j] - f) - 1e-9:
            j += 1
        # Blender shows file number (f - frame_start + 1) + offset at scene frame f
        offsets[f] = numbers[j] - (f - frame_start + 1)
    return SequencePlan(first, True, offsets, duration)


def plan_import(path, fps: int = 0) -> ImportPlan:
    """Load and validate a capture into an ImportPlan. Raises CaptureError; creates no bpy data."""
    cap = load_capture(path)
    all_frames = list(cap.frames) + list(cap.eval_frames)
    _validate_images(all_frames)
    by_cam = cap.frames_by_camera(include_eval=True)
    streams = {}
    for s in cap.spike_streams:
        streams.setdefault(s.camera, s)

    main = next((n for n, c in cap.cameras.items() if c.role == "train" and by_cam.get(n)), None)
    main = main or next((n for n in cap.cameras if by_cam.get(n)), None) or next(iter(cap.cameras), None)
    if main is None:
        raise CaptureError(cap.transforms_path or cap.root, "capture has no cameras")

    if fps <= 0:
        times = sorted({f.time for f in by_cam.get(main, [])})
        steps = [b - a for a, b in zip(times, times[1:]) if b - a > 1e-9]
        if steps:
            steps.sort()
            fps = max(1, int(round(1.0 / steps[len(steps) // 2])))
        else:
            fps = 30
    t0, t1 = cap.time_range
    if not (math.isfinite(t0) and math.isfinite(t1)):
        raise CaptureError(cap.transforms_path or cap.root, f"time range {cap.time_range} is not finite")
    frame_start = FRAME_START
    frame_end = frame_start + max(0, int(math.ceil((t1 - t0) * fps - 1e-6)))

    plan = ImportPlan(cap.root, cap.root.name, cap.format, [], main, int(fps), (t0, t1),
                      frame_start, frame_end, len(cap.frames), len(cap.eval_frames), list(cap.spike_streams))
    for name, info in cap.cameras.items():
        frames = by_cam.get(name, [])
        stream = streams.get(name)
        source = "frames"
        if frames:
            poses = [(f.time, f.c2w) for f in frames]
        elif stream is not None and stream.c2w is not None:
            poses, source = [(stream.t0, stream.c2w)], "spike stream"
        elif stream is not None and stream.co_located_with and by_cam.get(stream.co_located_with):
            f0 = by_cam[stream.co_located_with][0]
            poses, source = [(f0.time, f0.c2w)], f"co-located camera {stream.co_located_with}"
        else:
            poses, source = [(t0, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])], "none"
        moving = any(scene_build.poses_differ(poses[0][1], c2w) for _, c2w in poses[1:])
        cp = CameraPlan(name, info.intrinsics, info.role, poses, moving, len(frames),
                        frames[0].path if frames else None, stream, None, source)
        if frames:
            cp.sequence = _sequence_plan(frames, plan.frame_of, frame_start, frame_end)
        plan.cameras.append(cp)
    return plan


# ----------------------------------------------------------------------------- build (bpy data)

class _Created:
    """Datablocks created during one import, removed again if the import fails."""

    def __init__(self):
        self.items: list = []

    def add(self, idblock):
        self.items.append(idblock)
        return idblock

    def rollback(self):
        for idb in reversed(self.items):
            try:
                coll = {bpy.types.Object: bpy.data.objects, bpy.types.Camera: bpy.data.cameras,
                        bpy.types.Image: bpy.data.images, bpy.types.Collection: bpy.data.collections,
                        bpy.types.Action: bpy.data.actions}
                for cls, data in coll.items():
                    if isinstance(idb, cls):
                        data.remove(idb)
                        break
            except ReferenceError:
                pass
        self.items.clear()


def _set_constant(action) -> None:
    """Constant interpolation on the background-image frame-offset keys of ``action``."""
    for fc in scene_build.action_fcurves(action):
        if "frame_offset" in fc.data_path:
            for kp in fc.keyframe_points:
                kp.interpolation = "CONSTANT"


def _add_background(cam_obj, seq: SequencePlan, created: _Created, frame_start: int) -> None:
    img = created.add(bpy.data.images.load(str(seq.first_path), check_existing=False))
    if seq.is_sequence:
        img.source = "SEQUENCE"
    data = cam_obj.data
    data.show_background_images = True
    bg = data.background_images.new()
    bg.image = img
    bg.alpha = 1.0
    bg.display_depth = "BACK"
    bg.frame_method = "STRETCH"
    if not seq.is_sequence:
        return
    iu = bg.image_user
    iu.frame_start = frame_start
    iu.frame_duration = seq.duration
    iu.use_auto_refresh = True
    iu.use_cyclic = False
    values = set(seq.offsets.values())
    if len(values) == 1:
        iu.frame_offset = values.pop()
        return
    prev = None
    for f, off in sorted(seq.offsets.items()):
        if off != prev:
            iu.frame_offset = off
            iu.keyframe_insert("frame_offset", frame=f)
            prev = off
    iu.frame_offset = seq.offsets[frame_start]
    if data.animation_data and data.animation_data.action:
        created.add(data.animation_data.action)
        _set_constant(data.animation_data.action)


def _store_props(obj, cp: CameraPlan, plan: ImportPlan) -> None:
    k = cp.intrinsics
    obj["bt4d_camera"] = cp.name
    obj["bt4d_role"] = cp.role
    obj["bt4d_capture_dir"] = str(plan.root)
    obj["bt4d_intrinsics"] = {"w": int(k.width), "h": int(k.height), "fl_x": float(k.fx),
                              "fl_y": float(k.fy), "cx": float(k.cx), "cy": float(k.cy)}
    obj["bt4d_num_frames"] = int(cp.num_frames)
    obj["bt4d_first_frame"] = str(cp.first_frame) if cp.first_frame else ""
    obj["bt4d_pose_source"] = cp.pose_source
    obj["bt4d_moving"] = bool(cp.moving)
    s = cp.stream
    if s is not None:
        obj["bt4d_spike_file"] = str(s.path)
        obj["bt4d_spike_rate_hz"] = float(s.rate_hz)
        obj["bt4d_spike_frames"] = int(s.num_frames)
        obj["bt4d_spike_t0"] = float(s.t0)
        obj["bt4d_spike_size"] = [int(s.width), int(s.height)]
        obj["bt4d_co_located_with"] = s.co_located_with or ""


def build_scene(context, plan: ImportPlan, *, set_scene: bool = True, background_images: bool = True):
    """Create the collection and cameras of ``plan`` in ``context.scene``. Returns the collection."""
    scene = context.scene
    created = _Created()
    try:
        coll = created.add(bpy.data.collections.new(plan.name))
        scene.collection.children.link(coll)
        coll["bt4d_capture_dir"] = str(plan.root)
        coll["bt4d_fps"] = plan.fps
        coll["bt4d_frame_start"] = plan.frame_start
        coll["bt4d_time_start"] = plan.time_range[0]
        objects = {}
        for cp in plan.cameras:
            obj = blender_cameras.create_camera_object(cp.name, cp.intrinsics, cp.poses[0][1], coll)
            created.add(obj.data)
            created.add(obj)
            objects[cp.name] = obj
            _store_props(obj, cp, plan)
            if cp.moving:
                scene_build.keyframe_poses(obj, [(t - plan.time_range[0], m) for t, m in cp.poses],
                                           plan.fps, plan.frame_start)
                created.add(obj.animation_data.action)
            if background_images and cp.sequence is not None:
                _add_background(obj, cp.sequence, created, plan.frame_start)
        main = next(cp for cp in plan.cameras if cp.name == plan.main_camera)
        if set_scene:
            blender_cameras.configure_render(scene, main.intrinsics)
            scene.render.fps = plan.fps
            scene.render.fps_base = 1.0
            scene.frame_start = plan.frame_start
            scene.frame_end = plan.frame_end
            scene.camera = objects[plan.main_camera]
            scene.frame_set(plan.frame_start)
        s = scene.bt4d
        s.capture_dir = str(plan.root)
        s.capture_name = plan.name
        s.capture_collection = coll
        s.capture_format = plan.format
        s.num_cameras = len(plan.cameras)
        s.num_frames = plan.num_frames
        s.num_eval_frames = plan.num_eval_frames
        s.num_spike_streams = len(plan.streams)
        s.spike_summary = ", ".join(f"{st.camera} {st.rate_hz:g} Hz x {st.num_frames}" for st in plan.streams)
        s.time_start, s.time_end = plan.time_range
        s.main_camera = plan.main_camera
        return coll
    except Exception:
        created.rollback()
        raise


class BT4D_OT_import_capture(Operator):
    """Import a BulletTime4D capture folder (transforms.json): one camera per capture camera"""

    bl_idname = "bt4d.import_capture"
    bl_label = "Import Capture"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Capture Folder", subtype="DIR_PATH", options={"SKIP_SAVE"})
    filepath: StringProperty(name="File", subtype="FILE_PATH", options={"SKIP_SAVE", "HIDDEN"},
                             description="transforms.json (or transforms_train.json); its folder is imported")
    filter_folder: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_glob: StringProperty(default="*.json", options={"HIDDEN", "SKIP_SAVE"})
    fps: IntProperty(name="Scene FPS", default=0, min=0, max=10000,
                     description="Frame rate of the timeline; 0 uses the main train camera's frame rate")
    set_scene: BoolProperty(name="Set Up Scene", default=True,
                            description="Set resolution, frame rate, frame range and active camera")
    background_images: BoolProperty(name="Background Images", default=True,
                                     description="Show each camera's frames as its background image sequence")

    def _capture_path(self) -> str:
        fp = self.filepath
        if fp and Path(bpy.path.abspath(fp)).suffix.lower() == ".json":
            return bpy.path.abspath(fp)
        return bpy.path.abspath(self.directory or fp)

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = self._capture_path()
        if not path:
            self.report({"ERROR"}, "No capture folder given")
            return {"CANCELLED"}
        try:
            plan = plan_import(path, self.fps)
        except CaptureError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        try:
            coll = build_scene(context, plan, set_scene=self.set_scene, background_images=self.background_images)
        except Exception as err:  # noqa: BLE001 - reported, and the scene was rolled back
            self.report({"ERROR"}, f"{plan.root}: import failed: {err}")
            return {"CANCELLED"}
        moving = sum(cp.moving for cp in plan.cameras)
        self.report({"INFO"}, f"Imported {plan.name}: {len(plan.cameras)} cameras ({moving} moving) "
                              f"into collection {coll.name!r}, {plan.fps} FPS, frames "
                              f"{plan.frame_start}-{plan.frame_end}")
        return {"FINISHED"}


def menu_func_import(self, context):
    self.layout.operator(BT4D_OT_import_capture.bl_idname, text="BulletTime4D Capture")


classes = (BT4D_OT_import_capture,)


def register():
    bpy.types.TOPBAR_MT_file_import.append(menu_func_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_func_import)
