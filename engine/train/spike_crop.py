"""The spike loss's between-frame render cropped to where the spike view changes (issue 13).

The spike count loss (Eq. 17) at a between-frame instant ``t`` in ``[T1, T2)`` only has
something to say where the light changes inside that interval: a static pixel shows what the
RGB frames at both ends already supervise. So the render at the spike camera is made of the
*box* around the interval's change map (:class:`engine.spike.change.SpikeChange`, dilated by
``spike_crop_dilate`` blocks: motion blurs across block borders), aligned to the rasterizer's
8-pixel tiles, and the loss compares that box with the same pixels of the captured counts.

A crop is a pinhole camera of the same pose whose principal point is shifted by the box's
corner and whose image is the box (:func:`crop_view`): the rasterizer needs no change, and
the cropped render equals the same pixels of the full render (up to the projection's
field-of-view clamp of the Jacobian for Gaussians far outside the box, a few 1e-4 in
colour, ``tests/test_spike_crop.py``). The loss sums over the box and divides by the *full*
view's pixel count, so a pixel in the box gets the gradient it gets from the full-view loss
and the pixels outside get none.

The full view is used (:func:`crop_box` returns None) when the box covers more than
``spike_crop_max_frac`` of the view, when the render is not an integer multiple of the
sensor's size (the sensor resampling would not map the box onto whole sensor pixels), or
when no change map is known. Switch: ``TrainConfig.spike_crop``, **off**: the boxes cover
40-60 % of the view and a render's cost is mostly per Gaussian, so it saves ~3 % of a guided
step (bench-step, demo, CPU ms 87.4 -> 85.3; guided / RGB 1.91x -> 1.84x), and quality moves
either way (1000 fast steps, seeds 0 / 1, between frames: demo +0.57 / +0.24 dB, fast
-0.06 / -0.11, ``between`` +0.09 / -0.26; README "Spike guidance").
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["TILE", "crop_view", "mask_box", "align_box", "render_ratio", "crop_box", "crop_fraction"]

TILE = 8  # the rasterizer's tile size (engine.raster.rasterization's default)


def crop_view(vt: dict, box: tuple[int, int, int, int]) -> dict:
    """The view dict ``vt`` (viewmat, K [1, 3, 3], width, height, ...) seeing only the pixels
    ``box = (x0, y0, x1, y1)`` (x1, y1 exclusive) of its image: same pose and focal length,
    principal point moved by ``-(x0, y0)``, size ``(x1 - x0, y1 - y0)``."""
    x0, y0, x1, y1 = (int(v) for v in box)
    if not (0 <= x0 < x1 <= int(vt["width"]) and 0 <= y0 < y1 <= int(vt["height"])):
        raise ValueError(f"crop box {box} is not inside the {vt['width']}x{vt['height']} view")
    out = dict(vt)
    K = vt["K"].clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    out.update(K=K, width=x1 - x0, height=y1 - y0)
    return out


def mask_box(mask) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) bounding the True pixels of ``mask`` [h, w] (x1, y1 exclusive), or None."""
    m = np.asarray(mask.cpu().numpy() if isinstance(mask, torch.Tensor) else mask) > 0
    ys, xs = np.nonzero(m)
    if xs.size == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def align_box(box: tuple[int, int, int, int], align: int, width: int, height: int) -> tuple[int, int, int, int]:
    """``box`` grown outwards to multiples of ``align`` and clipped to ``width`` x ``height``."""
    a = max(1, int(align))
    x0, y0, x1, y1 = box
    return (max(0, x0 // a * a), max(0, y0 // a * a), min(int(width), -(-x1 // a) * a),
            min(int(height), -(-y1 // a) * a))


def render_ratio(render_wh: tuple[int, int], sensor_wh: tuple[int, int]) -> int | None:
    """Render pixels per sensor pixel when the render is the same whole multiple of the
    sensor's size in both axes (then a box of sensor pixels is a box of render pixels), else None."""
    (W, H), (w, h) = render_wh, sensor_wh
    if w <= 0 or h <= 0 or W % w or H % h or W // w != H // h or W // w < 1:
        return None
    return W // w


def crop_box(change, interval: int, sensor_wh: tuple[int, int], render_wh: tuple[int, int], *,
             dilate: int = 1, max_frac: float = 0.8) -> tuple[int, int, int, int] | None:
    """The box (x0, y0, x1, y1) in *sensor* pixels to render for an instant of ``interval``:
    the interval's change map (``change.gate_map(interval, dilate)``) bounded, grown to whole
    rasterizer tiles of the render, clipped; None for the full view (no change map, a box over
    ``max_frac`` of the view, a render that is not a whole multiple of the sensor). An interval
    without any change gets the full view too (it is not drawn when ``spike_skip_static``)."""
    r = render_ratio(render_wh, sensor_wh)
    if change is None or r is None or not (0 <= int(interval) < change.num_intervals):
        return None
    w, h = sensor_wh
    if tuple(change.shape) != (h, w):
        return None
    box = mask_box(change.gate_map(int(interval), int(dilate)))
    if box is None:
        return None
    align = TILE // r if TILE % r == 0 else 1
    box = align_box(box, align, w, h)
    if (box[2] - box[0]) * (box[3] - box[1]) > float(max_frac) * w * h:
        return None
    return box


def crop_fraction(box: tuple[int, int, int, int] | None, sensor_wh: tuple[int, int]) -> float:
    """Share of the view's pixels inside ``box`` (1 for None: the full view)."""
    if box is None:
        return 1.0
    x0, y0, x1, y1 = box
    return (x1 - x0) * (y1 - y0) / float(sensor_wh[0] * sensor_wh[1])
