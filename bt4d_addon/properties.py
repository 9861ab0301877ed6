"""The add-on's scene properties.

* ``Scene.bt4d``: the capture that was imported and the reconstruction settings. Capture
  summary fields are written by ``bt4d.import_capture``; the reconstruction settings
  (preset, seconds, output_dir, device, use_spikes, and the advanced motion choice and
  switches freeze_static / early_stop / close_cracks) are read by the training operator.
* ``Scene.bt4d_run``: the live state of a reconstruction / path render (progress, loss,
  PSNR, ETA, status) and the metrics of the last run, which the operators update from the
  main thread (``panel_run.py`` draws it).
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty
from bpy.types import PropertyGroup

PRESET_ITEMS = (  # the first is the default, as on the command line (tests/test_config.py checks it)
    ("fast", "Fast", "1,000 steps: the demo in under a minute on a laptop CPU. The default, and what every "
                     "published figure uses"),
    ("balanced", "Balanced", "2,500 steps and more Gaussians: a few minutes more for finer detail"),
    ("quality", "Quality", "3,000 steps, the most Gaussians and a finer motion grid: slowest"),
)
MOTION_ITEMS = (  # the engine setting motion.representation; the first is the engine's default
    ("trajectory", "Per-Gaussian Curves",
     "Every Gaussian follows its own smooth path through the RGB frames: fast objects stay sharp; "
     "the spike stream bends the paths between frames. The default"),
    ("hexplane", "Shared Motion Field",
     "One motion field shared by nearby Gaussians: smoother, but fast objects can turn into ghosts"),
    ("trajectory+hexplane", "Curves + Field",
     "Per-Gaussian paths with a shared motion field on top (slowest)"),
)
CRACK_FILL_ITEMS = (  # the engine setting losses.cover_grad; the first is the engine's default
    ("all", "Grow and Move",
     "Gaussians may grow, turn and move to cover cracks: best on most scenes"),
    ("opacities+means", "Move Only",
     "Gaussians only move and gain opacity: no streaks on finely textured surfaces at high "
     "resolution, but some holes may stay"),
)
DEVICE_ITEMS = (
    ("auto", "Auto", "CUDA when torch sees a GPU, otherwise the CPU"),
    ("cpu", "CPU", "Train on the CPU (slow but always available)"),
    ("cuda", "CUDA", "Train on the first CUDA GPU"),
)


class BT4D_SceneSettings(PropertyGroup):
    # -- capture (filled by bt4d.import_capture) ---------------------------------------
    capture_dir: StringProperty(
        name="Capture", subtype="DIR_PATH",
        description="Folder of the imported capture (holds transforms.json)")
    capture_name: StringProperty(name="Name", description="Name of the imported capture")
    capture_collection: PointerProperty(
        name="Collection", type=bpy.types.Collection,
        description="Collection holding the capture's cameras")
    capture_format: StringProperty(name="Format", description="Capture layout (bt4d, nerfstudio, dnerf)")
    num_cameras: IntProperty(name="Cameras", min=0)
    num_frames: IntProperty(name="Frames", min=0, description="Training RGB frames")
    num_eval_frames: IntProperty(name="Eval Frames", min=0, description="Held-out frames")
    num_spike_streams: IntProperty(name="Spike Streams", min=0)
    spike_summary: StringProperty(name="Spikes", description="Spike streams: camera, rate, frames")
    time_start: FloatProperty(name="Start", unit="TIME_ABSOLUTE", description="Capture start time (s)")
    time_end: FloatProperty(name="End", unit="TIME_ABSOLUTE", description="Capture end time (s)")
    main_camera: StringProperty(name="Main Camera", description="Train camera that sets the scene resolution")

    # -- reconstruction settings (read by the training operator) -----------------------
    preset: EnumProperty(name="Preset", items=PRESET_ITEMS, default=PRESET_ITEMS[0][0])
    seconds: FloatProperty(
        name="Time Budget", default=0.0, min=0.0, soft_max=7200.0, unit="TIME_ABSOLUTE",
        description="How long training may take. 0 (the default): the preset's own number of steps, as "
                    "on the command line. A budget sizes the run to fit it; a budget with time to spare "
                    "runs the preset's steps, settles, and finishes early once more steps stop paying")
    output_dir: StringProperty(
        name="Output", subtype="DIR_PATH", default="//bt4d_runs/",
        description="Where runs (checkpoints, exports, renders) are written")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="auto")
    use_spikes: BoolProperty(
        name="Use Spikes", default=True,
        description="Use the capture's spike stream to shape the motion between RGB frames (off: the RGB "
                    "frames alone)")
    # -- advanced: motion representation and skipping what the scene does not need ----------
    motion: EnumProperty(
        name="Motion", items=MOTION_ITEMS, default=MOTION_ITEMS[0][0],
        description="How the Gaussians move over time")
    freeze_static: BoolProperty(
        name="Freeze Static Gaussians", default=False,
        description="Gaussians that do not move stop being animated: faster training on scenes with a "
                    "static background")
    close_cracks: BoolProperty(
        name="Close Cracks at New Views", default=True,
        description="Keep what the cameras cover covered from viewpoints 10-20 degrees away; turn off for "
                    "scenes that really show empty space through "
                    "small gaps (wires, foliage)")
    crack_fill: EnumProperty(
        name="Fill Cracks By", items=CRACK_FILL_ITEMS, default=CRACK_FILL_ITEMS[0][0],
        description="What closing the cracks may change in the Gaussians")
    early_stop: BoolProperty(
        name="Stop Early", default=False,
        description="Stop training when the PSNR on a few train frames held back from training stops "
                    "improving (never the eval frames the result is scored on)")

    @property
    def has_capture(self) -> bool:
        return bool(self.capture_dir)


STATUS_ITEMS = (
    ("IDLE", "Idle", "Nothing has run yet"),
    ("RUNNING", "Running", "A reconstruction is running in the background"),
    ("FINISHED", "Finished", "The last reconstruction finished"),
    ("CANCELLED", "Cancelled", "The last reconstruction was cancelled (its checkpoint is kept)"),
    ("FAILED", "Failed", "The last reconstruction failed (see the message)"),
)


class BT4D_RunState(PropertyGroup):
    resume: BoolProperty(
        name="Resume", default=True,
        description="Continue from the run folder's checkpoint when its settings match; off: start over")
    num_samples: IntProperty(
        name="Time Samples", default=0, min=0, soft_max=400,
        description="Capture-time samples stored for playback in Blender (0: automatic, about 150 per second)")
    # live state ---------------------------------------------------------------------------
    status: EnumProperty(name="Status", items=STATUS_ITEMS, default="IDLE")
    stage: StringProperty(name="Stage")
    progress: FloatProperty(name="Progress", min=0.0, max=1.0, subtype="FACTOR")
    step: IntProperty(name="Step")
    total_steps: IntProperty(name="Steps")
    loss: FloatProperty(name="Loss", precision=4)
    psnr: FloatProperty(name="PSNR", precision=2, description="Training PSNR of the last step (dB)")
    eta_s: FloatProperty(name="ETA", unit="TIME_ABSOLUTE")
    elapsed_s: FloatProperty(name="Elapsed", unit="TIME_ABSOLUTE")
    num_gaussians: IntProperty(name="Gaussians")
    message: StringProperty(name="Message")
    run_dir: StringProperty(name="Run", subtype="DIR_PATH", description="Folder of the last reconstruction")
    # metrics (engine.evaluate) ------------------------------------------------------------
    has_metrics: BoolProperty(default=False)
    metric_psnr: FloatProperty(
        name="PSNR", precision=2,
        description="How closely the result matches the held-out camera's images, in dB. Higher is better: "
                    "above 25 looks clean, below 20 is visibly wrong")
    metric_ssim: FloatProperty(
        name="SSIM", precision=4,
        description="Structural similarity to the held-out images, 0 to 1. Higher is better: above 0.8 is good")
    metric_lpips: FloatProperty(
        name="LPIPS", precision=4, default=-1.0,
        description="Perceptual difference from the held-out images. Lower is better: below 0.1 is good, above "
                    "0.3 looks wrong (-1: not measured)")
    metric_psnr_interframe: FloatProperty(
        name="PSNR between RGB frames", precision=2,
        description="PSNR at instants between the RGB frames, where only the spike stream saw the scene. Higher "
                    "is better: within 1 dB of the overall PSNR is good")
    metric_psnr_dynamic: FloatProperty(
        name="PSNR dynamic regions", precision=2,
        description="PSNR on the pixels that move: the hardest part. Higher is better: above 20 dB is good")
    metric_frames: IntProperty(name="Eval frames")
    train_seconds: FloatProperty(name="Train time", unit="TIME_ABSOLUTE")
    # path render ---------------------------------------------------------------------------
    render_running: BoolProperty(default=False)
    render_progress: FloatProperty(name="Render", min=0.0, max=1.0, subtype="FACTOR")
    render_message: StringProperty(name="Render message")


classes = (BT4D_SceneSettings, BT4D_RunState)


def register():
    bpy.types.Scene.bt4d = PointerProperty(type=BT4D_SceneSettings)
    bpy.types.Scene.bt4d_run = PointerProperty(type=BT4D_RunState)


def unregister():
    for name in ("bt4d_run", "bt4d"):
        if hasattr(bpy.types.Scene, name):
            delattr(bpy.types.Scene, name)
