"""Fine-scale deformation feature from the spike stream (paper Eq. 6-10).

``f_fine = CA(MHA(F_tex + PE(t_i)), PE(t))`` and the deformation decoder receives
``f = f_coarse + f_fine`` (Eq. 10).

* Texture features (Eq. 7): the paper uses a frozen pretrained ResNet50; no weights are
  available offline, so :class:`SpikeTextureEncoder` is a small conv net over the TFP/TFI
  images of the K sub-windows (:mod:`engine.spike.features`). ``frozen_encoder=True`` keeps
  it at its random initialisation (a fixed random-feature extractor, frozen like the
  paper's), ``False`` trains it jointly. Training runs freeze it by default
  (``TrainConfig.fine_frozen_encoder``, issue 13): each window is then encoded once per run
  (:class:`EncodedWindows`) instead of twice per step, forward and backward, and on the
  demo it scored no worse (two seeds, docs/experiments/spike-guidance.md "Spike guidance").
* Time encoding (Eq. 8): sinusoidal, on the time relative to the window,
  ``(t - T1) / (T2 - T1)`` in [0, 1] (the same for the sub-window tokens and the query).
* MHA (Eq. 9): a Transformer encoder layer (``nn.MultiheadAttention`` + feed-forward) over
  the K tokens; CA: ``nn.MultiheadAttention`` with the query-time token as the query.
* Output: ``out_dim`` = the HexPlane feature width. The last projection starts at zero, so
  at initialisation ``f_fine = 0`` and the coarse model is unchanged.

Two granularities (``per_gaussian``):

* global (default): one feature per instant, from the whole spike image (adaptive pooled
  to a ``pool x pool`` grid per token), broadcast to every Gaussian;
* per-Gaussian: tokens are the conv feature maps sampled (``grid_sample``) at each
  Gaussian's projection into the spike view, so each Gaussian attends to the spike texture
  it actually covers. Gaussians that project outside the spike view get ``f_fine = 0``.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import RunError
from ..io.capture import load_capture
from ..raster.projection import pinhole_project
from ..spike.features import SpikeWindowCache

__all__ = ["sinusoidal_encoding", "SpikeTextureEncoder", "FineDeformation", "EncodedWindows", "SpikeFineEncoder",
           "project_to_grid", "count_parameters"]


def sinusoidal_encoding(x: torch.Tensor, dim: int, max_freq_log2: float | None = None) -> torch.Tensor:
    """Sinusoidal encoding of scalars ``x`` [...] (expected in ~[0, 1]) -> [..., dim].

    Frequencies ``pi * 2^k`` for ``k = 0 .. dim/2 - 1`` spread geometrically up to
    ``2^max_freq_log2`` (default ``dim/4``, capped at 10 octaves): low ones give the coarse
    position in the window, high ones separate neighbouring sub-windows.
    """
    half = dim // 2
    top = min(10.0, dim / 4) if max_freq_log2 is None else max_freq_log2
    freqs = math.pi * torch.pow(2.0, torch.linspace(0, top, half, device=x.device, dtype=torch.float32))
    ang = x.float()[..., None] * freqs
    enc = torch.cat([torch.sin(ang), torch.cos(ang)], -1)
    if enc.shape[-1] < dim:
        enc = F.pad(enc, (0, dim - enc.shape[-1]))
    return enc


class SpikeTextureEncoder(nn.Module):
    """Conv encoder for TFP/TFI images: [K, 2, h, w] -> feature map [K, C, h/4, w/4]."""

    def __init__(self, in_ch: int = 2, channels: int = 32):
        super().__init__()
        c = channels
        self.net = nn.Sequential(
            nn.Conv2d(in_ch, c // 2, 3, padding=1), nn.GELU(),
            nn.Conv2d(c // 2, c, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(c, c, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(c, c, 3, padding=1),
        )
        self.out_channels = c

    def forward(self, tex: torch.Tensor) -> torch.Tensor:
        # light estimates live in [0, 1]; centre them so random features are not all positive
        return self.net(tex * 2.0 - 0.5)


def project_to_grid(means: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int,
                    height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [N, 3] -> ``grid_sample`` coordinates [N, 2] in [-1, 1] (align_corners
    False) and a visibility mask [N] (in front of the camera and inside the image).
    ``viewmat`` is the OpenCV world-to-camera matrix (as the rasterizer takes)."""
    vm = torch.as_tensor(viewmat, dtype=means.dtype, device=means.device)
    Km = torch.as_tensor(K, dtype=means.dtype, device=means.device)
    uv, z = pinhole_project(means, vm, Km)
    gx = uv[:, 0] / width * 2.0 - 1.0
    gy = uv[:, 1] / height * 2.0 - 1.0
    grid = torch.stack([gx, gy], -1)
    vis = (z > 1e-3) & (gx.abs() <= 1.0) & (gy.abs() <= 1.0)
    return grid, vis


class FineDeformation(nn.Module):
    """E^f of Eq. 4: spike window + query time -> f_fine ([1, out_dim] or [N, out_dim])."""

    def __init__(self, out_dim: int, *, d_model: int = 64, heads: int = 4, ff_dim: int = 128,
                 channels: int = 32, pool: int = 4, per_gaussian: bool = False,
                 frozen_encoder: bool = False, dropout: float = 0.0):
        super().__init__()
        self.out_dim = int(out_dim)
        self.d_model = int(d_model)
        self.per_gaussian = bool(per_gaussian)
        self.pool = int(pool)
        self.encoder = SpikeTextureEncoder(2, channels)
        self.frozen_encoder = bool(frozen_encoder)
        if frozen_encoder:
            for p in self.encoder.parameters():
                p.requires_grad_(False)
        tok_in = channels if per_gaussian else channels * pool * pool
        self.token_proj = nn.Linear(tok_in, d_model)
        self.self_attn = nn.TransformerEncoderLayer(d_model, heads, ff_dim, dropout=dropout,
                                                    batch_first=True, norm_first=True)
        self.query_proj = nn.Linear(d_model, d_model)
        self.cross_attn = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        self.norm = nn.LayerNorm(d_model)
        self.out = nn.Linear(d_model, out_dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    # ------------------------------------------------------------------ pieces
    def _rel(self, times: torch.Tensor | float, t1: float, t2: float) -> torch.Tensor:
        span = max(float(t2) - float(t1), 1e-9)
        return (torch.as_tensor(times, dtype=torch.float32) - float(t1)) / span

    def features(self, tex: torch.Tensor) -> torch.Tensor:
        """Texture images [K, 2, h, w] -> conv feature maps [K, C, h', w']."""
        if self.frozen_encoder:
            with torch.no_grad():
                return self.encoder(tex)
        return self.encoder(tex)

    def encode(self, tex: torch.Tensor) -> torch.Tensor:
        """The query-independent part of one spike window (Eq. 7): its texture images
        [K, 2, h, w] through the conv encoder -- global: tokens pooled to ``pool x pool``
        [1, K, C * pool^2]; per-Gaussian: the feature maps [K, C, h', w']. This is what the
        spike branch costs (convolutions over K full spike images, forward and backward);
        :class:`EncodedWindows` keeps it per window."""
        fmap = self.features(tex.to(self.out.weight.device))   # [K, C, h', w']
        if self.per_gaussian:
            return fmap
        return F.adaptive_avg_pool2d(fmap, self.pool).reshape(1, fmap.shape[0], -1)

    def forward(self, window, t: float, *, grid: torch.Tensor | None = None,
                visible: torch.Tensor | None = None, encoded: torch.Tensor | None = None) -> torch.Tensor:
        """``window``: a :class:`engine.spike.features.SpikeWindow` (tex [K,2,h,w], times [K],
        t1, t2); ``t``: query time (s). Per-Gaussian mode needs ``grid`` [N, 2] (from
        :func:`project_to_grid`) and optionally ``visible`` [N]. ``encoded``: this window's
        :meth:`encode` when already computed."""
        dev = self.out.weight.device
        enc = self.encode(window.tex) if encoded is None else encoded
        K = enc.shape[1] if not self.per_gaussian else enc.shape[0]
        pe_tok = sinusoidal_encoding(self._rel(window.times.detach().cpu(), window.t1, window.t2),
                                     self.d_model).to(dev)     # [K, d]
        pe_q = sinusoidal_encoding(self._rel(torch.tensor([t]), window.t1, window.t2), self.d_model).to(dev)
        if not self.per_gaussian:
            x = self.token_proj(enc) + pe_tok[None]             # [1, K, d]
            q = self.query_proj(pe_q)[None]                     # [1, 1, d]
        else:
            if grid is None:
                raise ValueError("per-Gaussian fine deformation needs the Gaussians' projections (grid)")
            N = grid.shape[0]
            g = grid.to(dev, enc.dtype).reshape(1, 1, N, 2).expand(K, 1, N, 2)
            samp = F.grid_sample(enc, g, mode="bilinear", padding_mode="border", align_corners=False)
            tok = samp[:, :, 0, :].permute(2, 0, 1)             # [N, K, C]
            x = self.token_proj(tok) + pe_tok[None]             # [N, K, d]
            q = self.query_proj(pe_q)[None].expand(N, 1, self.d_model)
        x = self.self_attn(x)
        y, _ = self.cross_attn(q, x, x, need_weights=False)     # [B, 1, d]
        f = self.out(self.norm(y[:, 0] + q[:, 0]))              # [B, out_dim]
        if self.per_gaussian and visible is not None:
            f = f * visible.to(dev, f.dtype)[:, None]
        return f


def count_parameters(module: nn.Module, trainable_only: bool = True) -> int:
    return int(sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only))


# ----------------------------------------------------------------------------- encoded windows
class _Encoded:
    __slots__ = ("value", "versions", "clock", "live")

    def __init__(self, value, versions, clock):
        self.value, self.versions, self.clock, self.live = value, versions, clock, value.requires_grad


class EncodedWindows:
    """Per spike window, the conv encoder's output (:meth:`FineDeformation.encode`), so that
    the renders of a training step (the RGB frame's and the between-frame one) and of an
    evaluation do not run the encoder again on the same window (issue 13).

    ``get(key, params, compute)`` returns ``compute()`` or a kept value:

    * *same weights* (every ``params._version`` unchanged since it was computed): the kept
      value itself. With gradients on it must still hold its autograd graph (not yet
      consumed by a backward pass; a hook marks it): two renders of one step in the same
      window then share one encoder pass and one backward pass through it -- the same
      values and, up to float rounding, the same gradients as two passes. A frozen encoder
      (no trainable weights) is encoded once per window for the whole run.
    * *stale* (``refresh_every`` k > 1, gradients on): a value computed fewer than k steps
      ago (:meth:`tick` counts steps), detached: the encoder is trained, forward and
      backward, on a window's refresh steps only; the attention and the rest of the branch
      train every step on the kept tokens. This changes training
    (``FINE_ENCODER_EVERY`` of engine.train.guidance.spike_guidance).

    ``refresh_every`` 0 keeps nothing: every call encodes (the code path before issue 13).
    Weights written through ``.data`` (no version bump) are not seen: use ``clear()`` then.
    ``computed`` / ``shared`` / ``stale`` count the three outcomes (tests, bench-step)."""

    def __init__(self, refresh_every: int = 1):
        self.refresh_every = max(0, int(refresh_every))
        self.clock = 0
        self.computed = self.shared = self.stale = 0
        self._memo: dict = {}

    def __deepcopy__(self, memo):  # a copied model (the budget probe) starts with no kept values
        return EncodedWindows(self.refresh_every)

    def tick(self) -> None:
        """One training step done (the refresh clock of ``refresh_every``)."""
        self.clock += 1

    def clear(self) -> None:
        self._memo.clear()

    def get(self, key, params, compute):
        if self.refresh_every == 0:
            self.computed += 1
            return compute()
        params = list(params)
        versions = tuple(p._version for p in params)
        trains = torch.is_grad_enabled() and any(p.requires_grad for p in params)
        e = self._memo.get(key)
        if e is not None:
            if e.versions == versions and (not trains or e.live):
                self.shared += 1
                return e.value
            if trains and self.refresh_every > 1 and self.clock - e.clock < self.refresh_every:
                self.stale += 1
                return e.value.detach()
        value = compute()
        entry = _Encoded(value, versions, self.clock)
        if value.requires_grad:
            def consumed(_grad, entry=entry):  # backward reached it: its graph is gone
                entry.live = False
                entry.value = entry.value.detach()
            value.register_hook(consumed)
        self._memo[key] = entry
        self.computed += 1
        return value


# ----------------------------------------------------------------------------- spike fine encoder
class SpikeFineEncoder(nn.Module):
    """Deformation ``fine_encoder`` hook: (xyz_norm [N,3], t) -> [N, feature_dim]."""

    def __init__(self, feature_dim: int, spec: dict):
        super().__init__()
        self.spec = dict(spec)
        self.feature_dim = int(feature_dim)
        self.net = FineDeformation(feature_dim, d_model=int(spec.get("d_model", 64)),
                                   channels=int(spec.get("channels", 32)),
                                   per_gaussian=bool(spec.get("per_gaussian", False)),
                                   frozen_encoder=bool(spec.get("frozen_encoder", False)))
        self.register_buffer("bounds_min", torch.as_tensor(spec["bounds_min"], dtype=torch.float32))
        self.register_buffer("bounds_max", torch.as_tensor(spec["bounds_max"], dtype=torch.float32))
        self._cache: SpikeWindowCache | None = None
        self._tried = False
        # encoder output per window (issue 13); "encoder_every": engine.train.guidance.spike_guidance.FINE_ENCODER_EVERY
        self.encoded = EncodedWindows(int(spec.get("encoder_every", 1)))

    # --- data source ---------------------------------------------------------------------
    def attach(self, cache: SpikeWindowCache | None) -> None:
        self._cache, self._tried = cache, True
        self.encoded.clear()

    def source(self) -> SpikeWindowCache:
        """The spike windows: attached (training), stored in the checkpoint (runs saved
        since issue 11), else re-read from the capture recorded in the spec -- a RunError
        naming that path when it is gone (the branch never silently returns zeros: metrics
        would come from another model than the one trained)."""
        if self._cache is None:
            self._tried = True
            path = self.spec["capture"]
            try:
                cap = load_capture(path)
                stream = cap.spike_stream(self.spec["stream_camera"])
            except Exception as exc:
                raise RunError(path, "the run's spike fine branch needs this capture's spike stream "
                                     f"({self.spec['stream_camera']}) and the checkpoint does not store its "
                                     f"windows (an older run): restore the capture there, or retrain ({exc})") from exc
            self._cache = SpikeWindowCache(stream, self.spec["rgb_times"], k_sub=int(self.spec["k_sub"]))
        return self._cache

    def windows_state(self) -> dict | None:
        """The spike windows for the checkpoint (None when none could be read)."""
        try:
            return self.source().state()
        except Exception:
            return None

    def covers(self, t: float) -> bool:
        lo, hi = self.spec["coverage"]
        times = self.spec["rgb_times"]
        return lo - 1e-9 <= t <= hi + 1e-9 and times[0] - 1e-9 <= t <= times[-1] + 1e-9

    def forward(self, xyz_norm: torch.Tensor, t: float) -> torch.Tensor:
        n = xyz_norm.shape[0]
        zeros = xyz_norm.new_zeros(n, self.feature_dim)
        if not self.covers(float(t)):
            return zeros
        cache = self.source()
        win = cache.window(float(t))
        gated = bool(self.spec.get("change_gate", False))
        grid = vis = None
        if self.net.per_gaussian or gated:
            world = (xyz_norm + 1.0) * 0.5 * (self.bounds_max - self.bounds_min) + self.bounds_min
            v = self.spec["view"]
            grid, vis = project_to_grid(world.detach(), torch.as_tensor(v["viewmat"]), torch.as_tensor(v["K"]),
                                        int(v["width"]), int(v["height"]))
        # keyed by device too: Module.to() swaps parameter data without a version bump
        enc = self.encoded.get((int(win.index), str(self.net.out.weight.device)), self.net.encoder.parameters(),
                               lambda: self.net.encode(win.tex))
        if self.net.per_gaussian:
            f = self.net(win, float(t), grid=grid, visible=vis, encoded=enc)
        else:
            f = self.net(win, float(t), encoded=enc).expand(n, -1)
        if gated:
            f = f * self.change_gate(cache, win.index, grid, vis)[:, None]
        return f

    def change_gate(self, cache: SpikeWindowCache, interval: int, grid: torch.Tensor,
                    visible: torch.Tensor) -> torch.Tensor:
        """[N] in [0, 1]: 0 in windows without change and for Gaussians whose canonical
        position projects where the spike view never changes (engine.spike.change): static
        regions get no spike-driven motion. The map is the union over all windows because
        the canonical position of a moving object is where it is at t0, not at ``t``."""
        ch = cache.change(int(self.spec.get("change_block", 4)))
        if not bool(ch.changed[int(interval)].any()):
            return grid.new_zeros(grid.shape[0])
        g = ch.gate(None, grid, dilate=1)
        return g * visible.to(g.dtype)
