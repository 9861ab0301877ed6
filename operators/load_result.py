"""``bpy.ops.bt4d.load_result(directory=RUN)``: bring a reconstruction back into Blender.

The run's model (``engine.scene.model.load_run``) is sampled at K capture times (``Scene4D.sample``) and stored as one
mesh of N*K vertices packed in the .blend; a geometry-nodes modifier turns it into
ellipsoid instances animated by the keyframable "Capture Time" input
(``bt4d_addon/gaussian_nodes.py``, ``bt4d_addon/gaussian_material.py``). Nothing runs in
Python at playback or render time, so a saved .blend plays and renders anywhere.

Default animation: Capture Time is keyed linearly from the capture start at the scene's
first frame to the capture end ``(t1 - t0) * fps`` frames later (real time; constant
before and after). Hold it for bullet time, stretch the keys for slow motion.
"""
from __future__ import annotations

import math
from pathlib import Path

import bpy
from bpy.props import BoolProperty, IntProperty, StringProperty
from bpy.types import Operator

from ..bt4d_addon import attributes as A
from ..bt4d_addon import gaussian_material, gaussian_nodes, worker

COLLECTION_NAME = "BT4D Results"


def _collection(scene):
    coll = bpy.data.collections.get(COLLECTION_NAME)
    if coll is None:
        coll = bpy.data.collections.new(COLLECTION_NAME)
    if coll.name not in scene.collection.children:
        scene.collection.children.link(coll)
    return coll


def remove_result_object(obj) -> None:
    mesh = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if mesh is not None and mesh.users == 0:
        bpy.data.meshes.remove(mesh)


def load_samples(scene, samples: dict, run_dir: str, *, name: str | None = None, replace: bool = True,
                 key_time: bool = True, set_frame_range: bool = True, metrics: dict | None = None):
    """Build the result object from sampled arrays (main thread). Returns the object."""
    run_dir = str(run_dir)
    name = name or f"BT4D {Path(run_dir).name}"
    if replace:
        for obj in list(gaussian_nodes.find_result_objects(scene)):
            if obj.get(A.RUN_DIR) == run_dir:
                remove_result_object(obj)
    obj = gaussian_nodes.build_result_object(name, samples, collection=_collection(scene))
    obj[A.RUN_DIR] = run_dir
    if metrics:
        obj[A.METRICS] = {k: float(v) for k, v in metrics.items() if isinstance(v, (int, float))}
    gaussian_material.configure_scene_for_splats(scene)
    t0, t1 = float(samples["times"][0]), float(samples["times"][-1])
    if key_time:
        fe = gaussian_nodes.key_realtime(obj, scene, t0, t1)
        if set_frame_range and scene.frame_end < math.ceil(fe):
            scene.frame_end = int(math.ceil(fe))
    return obj


def load_run_into_scene(scene, run_dir: str, num_samples: int = 0, **kw):
    samples = worker.sample_run(run_dir, num_samples)
    return load_samples(scene, samples, run_dir, **kw)


class BT4D_OT_load_result(Operator):
    """Bring a reconstruction (run folder) back as animated Gaussians with a keyframable
    Capture Time"""

    bl_idname = "bt4d.load_result"
    bl_label = "Load Reconstruction"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Run Folder", subtype="DIR_PATH",
                              description="Run folder written by the reconstruction (holds checkpoint.pt)")
    num_samples: IntProperty(name="Time Samples", default=-1, min=-1, soft_max=400,
                             description="Stored capture-time samples (0: automatic; -1: the scene setting)")
    replace: BoolProperty(name="Replace", default=True,
                          description="Replace an object already loaded from this run")
    key_time: BoolProperty(name="Key Real Time", default=True,
                           description="Key Capture Time to follow the frame rate from the first frame")

    def invoke(self, context, event):
        if not self.directory:
            run = getattr(context.scene, "bt4d_run", None)
            if run is not None and run.run_dir:
                self.directory = run.run_dir
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        scene = context.scene
        run_dir = bpy.path.abspath(self.directory).rstrip("/\\") if self.directory else ""
        if not run_dir:
            self.report({"ERROR"}, "No run folder given")
            return {"CANCELLED"}
        k = self.num_samples
        if k < 0:
            run = getattr(scene, "bt4d_run", None)
            k = run.num_samples if run is not None else 0
        try:
            obj = load_run_into_scene(scene, run_dir, k, replace=self.replace, key_time=self.key_time)
        except Exception as exc:  # noqa: BLE001 - RunError and friends, shown verbatim
            self.report({"ERROR"}, f"Could not load the reconstruction: {exc}")
            return {"CANCELLED"}
        run = getattr(scene, "bt4d_run", None)
        if run is not None:
            run.run_dir = run_dir
        for o in context.view_layer.objects:
            o.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        n, k = obj.data[A.NUM_GAUSSIANS], obj.data[A.NUM_SAMPLES]
        self.report({"INFO"}, f"Loaded {n} Gaussians x {k} time samples as {obj.name!r}")
        return {"FINISHED"}


classes = (BT4D_OT_load_result,)
