"""Load a capture folder (CAPTURE_FORMAT.md) into plain records, without reading pixels.

Three layouts load:

1. **ours** — ``transforms.json`` with a ``cameras`` block, ``frames``, optional
   ``eval_frames`` and ``spike_streams``, optional ``points.ply``;
2. **D-NeRF** — ``transforms_train.json`` / ``transforms_val.json`` /
   ``transforms_test.json`` with ``camera_angle_x``; ``file_path`` has no extension
   (``.png`` is tried, then ``.exr``); ``time`` in [0, 1] is kept as seconds as-is.
   Train frames use camera ``train`` (role train), test frames camera ``test`` (role
   eval, in ``eval_frames``), val frames camera ``val`` (role eval, kept apart in
   ``Capture.val_frames``: never trained on, not scored);
3. **nerfstudio** — ``transforms.json`` without a ``cameras`` block: top-level
   ``fl_x, fl_y, cx, cy, w, h`` (or ``camera_angle_x``) and/or the same keys per frame.
   Frames with equal intrinsics share a camera (``cam0``, ``cam1``, ...). A frame without
   ``time`` is at time 0. ``ply_file_path`` names the point cloud. Lens distortion
   parameters are kept in ``CameraInfo.extra`` but not applied.

Spike streams (ours only): ``w``/``h`` default to the camera's and must match it;
``num_frames`` defaults to the whole file; ``transform_matrix`` defaults to the first pose of
the stream's camera, else of ``co_located_with``; optional ``head_cols`` / ``flipud`` are
passed to :func:`engine.io.spikes.read_spikes`.

Ground truth (ours only, optional; written by scripts/make_capture.py): a frame's
``depth_file_path`` names a single-channel float32 EXR (channel ``Z``) of planar depth in
metres, ``inf`` (or > 1e9) where no surface is (:meth:`Frame.load_depth`); a top-level
``ground_truth.objects`` block names an npz of moving objects' object-to-world matrices at
``rate_hz`` and surface samples (:class:`ObjectTruth`, :meth:`ObjectTruth.load`).

Everything the loader can check without decoding images is checked at load time and
reported as :class:`engine.errors.CaptureError` naming the file (and the frame / key) and
the problem. Image sizes are checked when a frame's pixels are loaded
(:meth:`Frame.load_rgb`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Intrinsics, View
from ..colour import linear_to_srgb
from ..errors import CaptureError
from . import images
from .ground_truth import GroundTruth, load_depth, parse_depth_path, parse_ground_truth
from .points import load_points
from .records import CheckContext, check_intrinsics, read_json, resolve_image
from .spikes import SpikeStream, count_frames, frame_bytes

ROLES = ("train", "eval")


# ----------------------------------------------------------------------------- records

@dataclass
class CameraInfo:
    """One capture camera: intrinsics (pixels) and role ("train" or "eval")."""

    name: str
    intrinsics: Intrinsics
    role: str = "train"
    extra: dict = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height


@dataclass
class Frame:
    """One RGB image: absolute path, camera name, time (s), camera-to-world (4x4, OpenGL)."""

    path: Path
    camera: str
    time: float
    c2w: np.ndarray
    intrinsics: Intrinsics | None = None
    role: str = "train"
    extra: dict = field(default_factory=dict)
    depth_file_path: Path | None = None  # ground-truth planar depth EXR (absolute), if the capture has it

    def load_depth(self) -> np.ndarray:
        """float32 [H, W] ground-truth planar depth (metres along the viewing axis); ``inf``
        where no surface is (values > 1e9 and non-finite ones are read as ``inf``)."""
        if self.depth_file_path is None:
            raise CaptureError(self.path, "frame has no ground-truth depth (no depth_file_path)")
        return load_depth(self.depth_file_path, self.intrinsics)

    def load_rgba(self) -> np.ndarray:
        """float32 [H, W, 4]: RGB sRGB-encoded in [0, 1] (EXR encoded and clipped), alpha."""
        img = images.read_image_rgba(self.path)
        finite = np.isfinite(img)
        if not finite.all():  # NaN/inf pixels would poison every gradient: reject, never clip
            raise CaptureError(self.path, "image contains non-finite values (NaN or inf) in "
                                          f"{int((~finite).any(axis=-1).sum())} pixel(s)")
        if self.intrinsics is not None:
            h, w = img.shape[:2]
            k = self.intrinsics
            if (w, h) != (k.width, k.height):
                raise CaptureError(self.path, f"image is {w}x{h} pixels but camera {self.camera!r} "
                                              f"expects {k.width}x{k.height}")
        if images.is_linear_file(self.path):
            img[..., :3] = np.clip(linear_to_srgb(img[..., :3]), 0.0, 1.0)
        return img

    def load_rgb(self, background=None) -> np.ndarray:
        """float32 [H, W, 3] sRGB-encoded in [0, 1] (the training convention).

        ``background`` (RGB in [0, 1], e.g. ``(1, 1, 1)`` for D-NeRF's white background):
        composite over it using the alpha channel; ``None`` drops alpha.
        """
        img = self.load_rgba()
        rgb = img[..., :3]
        if background is not None:
            a = img[..., 3:4]
            rgb = rgb * a + np.asarray(background, dtype=np.float32).reshape(1, 1, 3) * (1.0 - a)
        return np.ascontiguousarray(rgb, dtype=np.float32)

    def load_alpha(self) -> np.ndarray:
        """float32 [H, W] alpha (1 where the file has none)."""
        return np.ascontiguousarray(self.load_rgba()[..., 3])

    def view(self) -> View:
        if self.intrinsics is None:
            raise CaptureError(self.path, "frame has no intrinsics attached")
        return View(self.intrinsics, np.array(self.c2w, dtype=np.float64), float(self.time),
                    f"{self.camera}/{self.path.stem}", {"path": str(self.path), "camera": self.camera,
                                                         "role": self.role})


@dataclass
class SpikeStreamInfo:
    """A spike stream record from transforms.json (validated; open it with :meth:`open`)."""

    path: Path
    camera: str
    rate_hz: float
    t0: float
    num_frames: int
    width: int
    height: int
    co_located_with: str | None = None
    c2w: np.ndarray | None = None
    intrinsics: Intrinsics | None = None
    head_cols: int = 0
    flipud: bool = True

    @property
    def t_end(self) -> float:
        return self.t0 + self.num_frames / self.rate_hz

    def open(self) -> SpikeStream:
        return SpikeStream(self.path, self.width, self.height, self.rate_hz, self.t0, self.num_frames,
                           camera=self.camera, co_located_with=self.co_located_with, c2w=self.c2w,
                           intrinsics=self.intrinsics, flipud=self.flipud, head_cols=self.head_cols)


@dataclass
class Capture:
    """A loaded capture. ``frames`` are the training RGB frames (train-role cameras);
    ``eval_frames`` the held-out ones (``eval_frames`` of the file plus frames of
    eval-role cameras)."""

    root: Path
    cameras: dict[str, CameraInfo]
    frames: list[Frame]
    eval_frames: list[Frame]
    spike_streams: list[SpikeStreamInfo]
    points_path: Path | None
    time_range: tuple[float, float]
    format: str = "bt4d"
    transforms_path: Path | None = None
    val_frames: list[Frame] = field(default_factory=list)
    ground_truth: "GroundTruth | None" = None

    def __repr__(self) -> str:
        return (f"Capture({str(self.root)!r}, format={self.format}, cameras={list(self.cameras)}, "
                f"{len(self.frames)} frames, {len(self.eval_frames)} eval frames, "
                f"{len(self.spike_streams)} spike streams, time {self.time_range})")

    def cameras_with_role(self, role: str) -> list[str]:
        return [n for n, c in self.cameras.items() if c.role == role]

    def train_frames(self, camera: str | None = None) -> list[Frame]:
        """Training frames (optionally of one camera), in file order."""
        out = [f for f in self.frames if f.role == "train"]
        return out if camera is None else [f for f in out if f.camera == camera]

    def frames_by_camera(self, include_eval: bool = True) -> dict[str, list[Frame]]:
        """camera name -> its frames sorted by time (eval frames included by default)."""
        groups: dict[str, list[Frame]] = {}
        for f in self.frames + (self.eval_frames if include_eval else []):
            groups.setdefault(f.camera, []).append(f)
        return {k: sorted(v, key=lambda fr: fr.time) for k, v in groups.items()}

    def rgb_times(self, camera: str) -> np.ndarray:
        """Sorted times (float64) of one camera's frames (train or eval)."""
        if camera not in self.cameras:
            raise KeyError(f"unknown camera {camera!r}; cameras are {list(self.cameras)}")
        return np.array(sorted(f.time for f in self.frames + self.eval_frames if f.camera == camera),
                        dtype=np.float64)

    def view(self, frame: Frame) -> View:
        return frame.view()

    def spike_stream(self, camera_name: str | None = None) -> SpikeStream:
        """Open the spike stream of a camera (or the only/first one when ``None``)."""
        if not self.spike_streams:
            raise CaptureError(self.transforms_path or self.root, "capture has no spike streams")
        if camera_name is None:
            return self.spike_streams[0].open()
        for s in self.spike_streams:
            if s.camera == camera_name:
                return s.open()
        raise KeyError(f"no spike stream for camera {camera_name!r}; streams: "
                       f"{[s.camera for s in self.spike_streams]}")

    def load_points(self):
        """(xyz, rgb or None) from the capture's point cloud, or None when it has none."""
        return None if self.points_path is None else load_points(self.points_path)


def _time_range(frames: list[Frame], streams: list[SpikeStreamInfo]) -> tuple[float, float]:
    ts = [f.time for f in frames]
    for s in streams:
        ts += [s.t0, s.t_end]
    return (float(min(ts)), float(max(ts))) if ts else (0.0, 0.0)


def _find_points(root: Path, data: dict, ctx: CheckContext) -> Path | None:
    for key in ("points", "ply_file_path"):
        if key in data:
            rel = ctx.string(data[key], key)
            p = Path(rel) if Path(rel).is_absolute() else root / rel
            if not p.is_file():
                ctx.fail(key, f"point cloud file {rel!r} does not exist ({p})")
            return p.resolve()
    p = root / "points.ply"
    return p.resolve() if p.is_file() else None


# ----------------------------------------------------------------------------- loaders

def _refuse_conflicting_frames(ctx: CheckContext, entries: list[tuple[str, Frame]], *, same_pose_only: bool) -> None:
    """Refuse two frames of one camera at one capture time (issue 45): which image trains that
    instant would be a silent choice. ``entries``: (where, frame) in file order. In our format a
    camera is one device, so any pair conflicts; nerfstudio / D-NeRF group frames into cameras
    by intrinsics (many poses at t = 0 is a static multi-view capture), so there only a pair that
    also shares the pose conflicts."""
    seen: dict[tuple, tuple[str, Frame]] = {}
    for where, f in entries:
        key = (f.camera, round(float(f.time), 9))
        if same_pose_only:
            key += (tuple(np.round(np.asarray(f.c2w, np.float64), 9).ravel().tolist()),)
        first, other = seen.setdefault(key, (where, f))
        if first != where:
            same = " (the same image listed twice)" if Path(other.path) == Path(f.path) else ""
            ctx.fail(where, f"camera {f.camera!r} already has a frame at time {float(f.time):g} s in {first}{same}; "
                            "two frames of one camera at one instant conflict: remove one or give it its own camera")


def _load_ours(root: Path, tpath: Path, data: dict) -> Capture:
    ctx = CheckContext(tpath)
    cams_raw = data["cameras"]
    if not isinstance(cams_raw, dict) or not cams_raw:
        ctx.fail("cameras", "must be a non-empty object mapping camera names to intrinsics")
    cameras: dict[str, CameraInfo] = {}
    for name, c in cams_raw.items():
        where = f"cameras[{name!r}]"
        if not isinstance(c, dict):
            ctx.fail(where, "must be an object")
        role = c.get("role", "train")
        if role not in ROLES:
            ctx.fail(f"{where}.role", f"must be one of {ROLES}, got {role!r}")
        extra = {k: v for k, v in c.items() if k not in ("w", "h", "fl_x", "fl_y", "cx", "cy", "role",
                                                          "camera_angle_x", "camera_angle_y")}
        cameras[name] = CameraInfo(name, check_intrinsics(ctx, c, where), role, extra)

    def frame(d, where, default_role) -> Frame:
        if not isinstance(d, dict):
            ctx.fail(where, "must be an object")
        cam = ctx.string(ctx.get(d, "camera", where), f"{where}.camera")
        if cam not in cameras:
            ctx.fail(f"{where}.camera", f"unknown camera {cam!r}; cameras are {sorted(cameras)}")
        fp = ctx.string(ctx.get(d, "file_path", where), f"{where}.file_path")
        path = resolve_image(ctx, root, fp, f"{where}.file_path", try_suffixes=False)
        t = ctx.num(ctx.get(d, "time", where), f"{where}.time")
        c2w = ctx.matrix(ctx.get(d, "transform_matrix", where), f"{where}.transform_matrix")
        role = "eval" if default_role == "eval" else cameras[cam].role
        depth = parse_depth_path(ctx, root, d, where)
        return Frame(path, cam, t, c2w, cameras[cam].intrinsics, role, depth_file_path=depth)

    all_frames = [frame(d, f"frames[{i}]", "train") for i, d in enumerate(ctx.list_of(data, "frames", required=True))]
    frames = [f for f in all_frames if f.role == "train"]
    eval_extra = [frame(d, f"eval_frames[{i}]", "eval")
                  for i, d in enumerate(ctx.list_of(data, "eval_frames", required=False))]
    eval_frames = eval_extra
    eval_frames = [f for f in all_frames if f.role == "eval"] + eval_frames
    _refuse_conflicting_frames(ctx, [(f"frames[{i}]", f) for i, f in enumerate(all_frames)]
                               + [(f"eval_frames[{i}]", f) for i, f in enumerate(eval_extra)], same_pose_only=False)

    first_pose = {}
    for f in all_frames + eval_frames:
        first_pose.setdefault(f.camera, f.c2w)
    streams: list[SpikeStreamInfo] = []
    for i, d in enumerate(ctx.list_of(data, "spike_streams", required=False)):
        where = f"spike_streams[{i}]"
        if not isinstance(d, dict):
            ctx.fail(where, "must be an object")
        cam = ctx.string(ctx.get(d, "camera", where), f"{where}.camera")
        if cam not in cameras:
            ctx.fail(f"{where}.camera", f"unknown camera {cam!r}; cameras are {sorted(cameras)}")
        co = d.get("co_located_with")
        if co is not None:
            co = ctx.string(co, f"{where}.co_located_with")
            if co not in cameras:
                ctx.fail(f"{where}.co_located_with", f"unknown camera {co!r}; cameras are {sorted(cameras)}")
        rate = ctx.num(ctx.get(d, "rate_hz", where), f"{where}.rate_hz", positive=True)
        t0 = ctx.num(d.get("t0", 0.0), f"{where}.t0")
        k = cameras[cam].intrinsics
        w = ctx.num(d.get("w", k.width), f"{where}.w", positive=True, integer=True)
        h = ctx.num(d.get("h", k.height), f"{where}.h", positive=True, integer=True)
        if (w, h) != (k.width, k.height):
            ctx.fail(where, f"stream is {w}x{h} but camera {cam!r} is {k.width}x{k.height}")
        head_cols = ctx.num(d.get("head_cols", 0), f"{where}.head_cols", integer=True)
        flipud = bool(d.get("flipud", True))
        fp = ctx.string(ctx.get(d, "file_path", where), f"{where}.file_path")
        spath = (Path(fp) if Path(fp).is_absolute() else root / fp)
        if not spath.is_file():
            ctx.fail(f"{where}.file_path", f"spike file {fp!r} does not exist ({spath})")
        try:
            frame_bytes(h, w, head_cols)
        except ValueError as exc:
            ctx.fail(where, str(exc))
        on_disk = count_frames(spath, h, w, head_cols=head_cols)  # CaptureError names the .dat
        if "num_frames" in d:
            n = ctx.num(d["num_frames"], f"{where}.num_frames", integer=True)
            if n < 0 or n > on_disk:
                ctx.fail(f"{where}.num_frames", f"is {n} but {spath.name} holds {on_disk} frames")
        else:
            n = on_disk
        if "transform_matrix" in d:
            c2w = ctx.matrix(d["transform_matrix"], f"{where}.transform_matrix")
        else:
            c2w = first_pose.get(cam, first_pose.get(co) if co else None)
        streams.append(SpikeStreamInfo(spath.resolve(), cam, rate, t0, int(n), int(w), int(h), co,
                                       None if c2w is None else np.array(c2w), k, int(head_cols), flipud))

    cap = Capture(root, cameras, frames, eval_frames, streams, _find_points(root, data, ctx),
                  _time_range(frames + eval_frames, streams), "bt4d", tpath)
    if "ground_truth" in data:
        cap.ground_truth = parse_ground_truth(ctx, root, data["ground_truth"])
    return cap


def _load_nerfstudio(root: Path, tpath: Path, data: dict) -> Capture:
    ctx = CheckContext(tpath)
    raw_frames = ctx.list_of(data, "frames", required=True)
    top = {k: data[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y")
           if k in data}
    distortion = {k: data[k] for k in ("camera_model", "k1", "k2", "k3", "k4", "p1", "p2") if k in data}
    cameras: dict[str, CameraInfo] = {}
    by_key: dict[tuple, str] = {}
    frames: list[Frame] = []
    for i, d in enumerate(raw_frames):
        where = f"frames[{i}]"
        if not isinstance(d, dict):
            ctx.fail(where, "must be an object")
        fp = ctx.string(ctx.get(d, "file_path", where), f"{where}.file_path")
        path = resolve_image(ctx, root, fp, f"{where}.file_path", try_suffixes=True)
        c2w = ctx.matrix(ctx.get(d, "transform_matrix", where), f"{where}.transform_matrix")
        t = ctx.num(d["time"], f"{where}.time") if "time" in d else 0.0
        k = check_intrinsics(ctx, d, where, top, size_from=lambda p=path: images.read_image_size(p))
        key = (k.width, k.height, k.fx, k.fy, k.cx, k.cy)
        if key not in by_key:
            name = f"cam{len(by_key)}"
            by_key[key] = name
            cameras[name] = CameraInfo(name, k, "train", dict(distortion))
        frames.append(Frame(path, by_key[key], t, c2w, k, "train"))
    _refuse_conflicting_frames(ctx, [(f"frames[{i}]", f) for i, f in enumerate(frames)], same_pose_only=True)
    return Capture(root, cameras, frames, [], [], _find_points(root, data, ctx),
                   _time_range(frames, []), "nerfstudio", tpath)


def _load_dnerf(root: Path) -> Capture:
    cameras: dict[str, CameraInfo] = {}
    split_frames: dict[str, list[Frame]] = {"train": [], "val": [], "test": []}
    points = None
    for split, role in (("train", "train"), ("val", "eval"), ("test", "eval")):
        tpath = root / f"transforms_{split}.json"
        if not tpath.is_file():
            if split == "train":
                raise CaptureError(tpath, "file does not exist")
            continue
        data = read_json(tpath)
        ctx = CheckContext(tpath)
        raw = ctx.list_of(data, "frames", required=True)
        paths = []
        for i, d in enumerate(raw):
            where = f"frames[{i}]"
            fp = ctx.string(ctx.get(d, "file_path", where), f"{where}.file_path")
            paths.append(resolve_image(ctx, root, fp, f"{where}.file_path", try_suffixes=True))
        if not paths:
            k = None
        else:
            k = check_intrinsics(ctx, data, "", size_from=lambda p=paths[0]: images.read_image_size(p))
        if k is not None:
            cameras[split] = CameraInfo(split, k, role)
        for i, (d, path) in enumerate(zip(raw, paths)):
            where = f"frames[{i}]"
            c2w = ctx.matrix(ctx.get(d, "transform_matrix", where), f"{where}.transform_matrix")
            t = ctx.num(d["time"], f"{where}.time") if "time" in d else 0.0
            split_frames[split].append(Frame(path, split, t, c2w, k, role))
        _refuse_conflicting_frames(ctx, [(f"frames[{i}]", f) for i, f in enumerate(split_frames[split])],
                                   same_pose_only=True)
        if split == "train":
            points = _find_points(root, data, ctx)
    frames, evals = split_frames["train"], split_frames["test"]
    cap = Capture(root, cameras, frames, evals, [], points, _time_range(frames + evals, []), "dnerf",
                  root / "transforms_train.json", split_frames["val"])
    return cap


def load_capture(path: str | Path) -> Capture:
    """Load a capture folder (or its transforms*.json file). Reads no pixels.

    Raises CaptureError naming the file and the problem for anything unusable.
    """
    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        root = path.parent
        if path.name.startswith("transforms_"):
            return _load_dnerf(root.resolve())
        tpath = path
    else:
        root = path
        if not root.exists():
            raise CaptureError(root, "capture folder does not exist")
        if not root.is_dir():
            raise CaptureError(root, "not a folder or a transforms .json file")
        tpath = root / "transforms.json"
        if not tpath.is_file():
            if (root / "transforms_train.json").is_file():
                return _load_dnerf(root.resolve())
            raise CaptureError(tpath, "missing transforms.json (not a capture folder; no transforms_train.json either)")
    root = root.resolve()
    tpath = tpath.resolve()
    data = read_json(tpath)
    if "cameras" in data:
        return _load_ours(root, tpath, data)
    return _load_nerfstudio(root, tpath, data)
