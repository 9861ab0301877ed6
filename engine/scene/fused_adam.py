"""Adam in three passes per parameter instead of seven, bit for bit torch's (issue 13).

With per-Gaussian trajectories the Gaussians carry ~190 floats each (133 of them the
curves' control points, ``engine.scene.trajectory``), and ``torch.optim.Adam``'s CPU
single-tensor step walks every parameter seven times (``lerp_``, ``mul_``, ``addcmul_``,
``sqrt``, ``div``, ``add_``, ``addcdiv_``): 15-16 ms of a 80-90 ms RGB deformation step on
the demo (docs/experiments/benchmark-history.md), most of it in ``sqrt``: torch's CPU square root (MKL)
takes a slow path on zeros, and ~70 % of the curves' moments are zero (columns no render
has reached yet). :class:`FusedAdam` is ``torch.optim.Adam`` (same constructor, state,
``state_dict``, so densification's state surgery and checkpoints are unchanged) whose
``step`` updates the moments in one numba pass, takes torch's ``sqrt`` of the nonzero ones
(zeros replaced by 1, their root set back to 0), and updates the parameter in a second
numba pass (:mod:`engine.scene._adam_kernels`), rounding exactly as torch does. Where
torch's ``sqrt`` is MKL's ``vmsSqrt`` (torch's x86 wheels; :mod:`engine.numba_vml`) the three
stages run in one numba pass, :data:`BLOCK` elements at a time, calling ``vmsSqrt``
itself: every array streams from memory once (28 bytes per float instead of ~60), 1.4x
faster on a 5M-float state (11.7 -> 8.2 ms CPU, one thread, load ~4; ``/tmp`` micro-benchmark
in the sparseadam report), the same numbers.
``torch.optim.Adam(fused=True)`` is faster still but not the same numbers (+-1 ulp in ~5 %
of the elements per step, measured), so training would no longer reproduce runs made
before.

Exactness rests on how torch's CPU kernels round (fused multiply-adds in ``lerp_`` and
``addcmul_``), so :func:`exact` compares one step on random tensors with torch's before
the fused path is used, once per process; anything it does not cover (CUDA, float64,
non-contiguous or sparse tensors, amsgrad, weight decay, maximize, tensor learning rates,
no numba) takes torch's own step.
"""
from __future__ import annotations

import numpy as np
import torch

from ..numba_cache import LazyKernels

KERNELS = LazyKernels(__package__, "_adam_kernels")

# False: every step is torch's (bench-step's "adam-torch" variant switches it)
ENABLED = True
# False: the two-pass kernels with torch's sqrt between them (bench-step's "adam-twopass")
ONE_PASS = True
BLOCK = 16384  # one pass's block: 5 arrays x 64 KiB stay in the 512 KiB L2 (8k-32k measured alike)
# False: a parameter's one-pass update runs on one thread (bench-step's "adam-serial"). True: a
# large one (the curves) is cut into runs of whole blocks, one per numba thread (at most
# MAX_THREADS; _adam_kernels.step_threads): the pass is memory bound and one core does not fill
# the memory bus (docs/experiments/benchmark-history.md "Adam on numba's threads"). Elementwise: the same numbers.
PARALLEL = True
PARALLEL_MIN = 1 << 18  # floats: below this, the thread hand-off costs more than it saves
MAX_THREADS = 4
_EXACT: bool | None = None
_ONE_PASS_EXACT: bool | None = None


def _supported(p: torch.Tensor) -> bool:
    g = p.grad
    return (p.device.type == "cpu" and p.dtype == torch.float32 and p.is_contiguous() and g is not None
            and not g.is_sparse and g.dtype == torch.float32 and g.is_contiguous() and g.shape == p.shape)


def _fused_update(p, grad, m, v, step: float, lr: float, beta1: float, beta2: float, eps: float,
                  scratch: torch.Tensor, one_pass: bool | None = None) -> None:
    """One Adam update of ``p`` (in place, with its moments) for the ``step``-th time;
    the scalars as ``_single_tensor_adam`` computes them, then rounded to float32.
    ``scratch``: float32, at least ``min(p.numel(), BLOCK)`` long with ``one_pass``, else at
    least ``p.numel()`` (the square roots). ``one_pass``: None = where exact
    (:func:`one_pass_exact`)."""
    k = KERNELS.module
    f32 = np.float32  # torch rounds a Python scalar to the tensor's float32 the same way (nearest)
    bias_correction1 = 1 - beta1 ** step
    bias_correction2 = 1 - beta2 ** step
    step_size = lr / bias_correction1
    bias_correction2_sqrt = bias_correction2 ** 0.5
    pf, gf, mf, vf = (t.detach().view(-1).numpy() for t in (p, grad, m, v))
    if pf.size == 0:
        return
    if one_pass is None:
        one_pass = ONE_PASS and one_pass_exact()
    if one_pass:
        scalars = (f32(1 - beta1), f32(beta2), f32(1 - beta2), f32(bias_correction2_sqrt), f32(eps), f32(-step_size))
        cuts = _thread_cuts(pf.size)
        if len(cuts) > 2:  # runs of whole blocks on numba's threads, a scratch block each
            bufs = scratch[:(len(cuts) - 1) * BLOCK].view(len(cuts) - 1, BLOCK).numpy()
            k.step_threads(pf, gf, mf, vf, *scalars, bufs, cuts[1])
        else:
            k.step(pf, gf, mf, vf, *scalars, scratch[:min(BLOCK, pf.size)].numpy())
        return
    root = scratch[:pf.size]
    k.moments(gf, mf, vf, f32(1 - beta1), f32(beta2), f32(1 - beta2), root.numpy())
    torch.sqrt(root, out=root)  # torch's (MKL's) rounding
    k.update(pf, mf, vf, root.numpy(), f32(bias_correction2_sqrt), f32(eps), f32(-step_size))


def _thread_cuts(n: int) -> list[int]:
    """Element offsets [0, .., n] of the runs of whole blocks the threads update (one run
    when :data:`PARALLEL` is off or ``n`` < :data:`PARALLEL_MIN`)."""
    blocks, threads = -(-n // BLOCK), 1
    if PARALLEL and n >= PARALLEL_MIN:
        import numba

        threads = max(1, min(MAX_THREADS, numba.get_num_threads(), blocks))
    per = -(-blocks // threads) * BLOCK  # whole blocks per thread, in elements
    return sorted({min(n, i * per) for i in range(threads)} | {n})


def exact() -> bool:
    """True when the fused path gives torch's Adam bit for bit here (checked once: three
    steps on random tensors of awkward sizes, against ``torch.optim.Adam``)."""
    global _EXACT
    if _EXACT is None:
        _EXACT = False
        if KERNELS.load() is not None:
            try:
                _EXACT = _self_check(one_pass=False)
            except Exception:  # a numba / llvmlite that cannot compile the kernels: torch's path
                _EXACT = False
    return _EXACT


def one_pass_exact() -> bool:
    """True when the one-pass kernel (:mod:`engine.numba_vml`'s ``vmsSqrt``) gives torch's
    Adam bit for bit here: the two-pass path is exact, ``vmsSqrt`` is exported, its roots
    equal ``torch.sqrt``'s on a probe of every float32 magnitude (subnormals, inf, NaN, odd
    lengths and offsets), and the self-check's steps agree. Checked once per process."""
    global _ONE_PASS_EXACT
    if _ONE_PASS_EXACT is None:
        _ONE_PASS_EXACT = False
        if exact():
            try:
                from .. import numba_vml

                _ONE_PASS_EXACT = numba_vml.AVAILABLE and _sqrt_probe() and _self_check(one_pass=True)
            except Exception:  # no vmsSqrt, or a numba that cannot link it: the two passes
                _ONE_PASS_EXACT = False
    return _ONE_PASS_EXACT


def _sqrt_probe() -> bool:
    gen = torch.Generator().manual_seed(4321)
    bits = torch.randint(0, 2 ** 31 - 1, (200_003,), generator=gen, dtype=torch.int64).to(torch.int32)
    x = bits.view(torch.float32)  # every non-negative float32 pattern class: subnormal .. inf, NaN
    x = torch.cat([x, torch.tensor([0.0, 1.0, float("inf"), 1e-45, 3.4e38]), torch.rand(77_777, generator=gen)])
    ref = torch.sqrt(x)
    k = KERNELS.module
    for lo in (0, 1, 3, 17):  # odd offsets and lengths: MKL's vector body against its scalar tail
        out = torch.empty_like(x)
        k.vml_sqrt(x[lo:].numpy(), out[lo:].numpy())
        if not torch.equal(out[lo:].view(torch.int32), ref[lo:].view(torch.int32)):
            return False
    return True


def _self_check(one_pass: bool) -> bool:
    gen = torch.Generator().manual_seed(12345)
    sizes = [(1,), (7,), (37, 3), (2053, 19, 4)]
    mk = lambda: [torch.nn.Parameter(torch.randn(s, generator=torch.Generator().manual_seed(i)) *  # noqa: E731
                                     10.0 ** (i - 3)) for i, s in enumerate(sizes)]
    ref, fus = mk(), mk()
    groups = lambda ps: [{"params": [p], "lr": 10.0 ** -(i + 1)} for i, p in enumerate(ps)]  # noqa: E731
    o_ref = torch.optim.Adam(groups(ref), lr=0.0, eps=1e-15, foreach=False)
    o_fus = FusedAdam(groups(fus), lr=0.0, eps=1e-15)
    for _ in range(3):
        for a, b in zip(ref, fus):
            gr = torch.randn(a.shape, generator=gen) * torch.rand(a.shape, generator=gen).pow(8) * 10.0
            gr *= torch.rand(a.shape, generator=gen) < 0.5  # exact zeros, as in untouched columns
            gr.view(-1)[: gr.numel() // 3] = 0.0  # a block never touched: zero moments
            a.grad, b.grad = gr.clone(), gr.clone()
        o_ref.step()
        o_fus._fused_step(one_pass)
    return all(torch.equal(a, b) and torch.equal(o_ref.state[a]["exp_avg"], o_fus.state[b]["exp_avg"])
               and torch.equal(o_ref.state[a]["exp_avg_sq"], o_fus.state[b]["exp_avg_sq"]) for a, b in zip(ref, fus))


def torch_adam_update(p, grad, m, v, step: float, lr: float, betas, eps: float) -> None:
    """``torch.optim.adam._single_tensor_adam``'s update (no weight decay, amsgrad or maximize) in
    place, in torch ops: the plain-torch reference of the fused passes (the selective and lazy
    steps' references, the lazy step's fallback off the CPU)."""
    beta1, beta2 = betas
    m.lerp_(grad, 1 - beta1)
    v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
    denom = (v.sqrt() / ((1 - beta2 ** step) ** 0.5)).add_(eps)
    p.addcdiv_(m, denom, value=-(lr / (1 - beta1 ** step)))


def adam_moments(state: dict, p: torch.Tensor, who: str) -> tuple[torch.Tensor, torch.Tensor]:
    """``p``'s Adam moments (exp_avg, exp_avg_sq), created on first use as
    torch.optim.Adam._init_group does, with the step count advanced; they must be contiguous
    float32 (the numba passes read them flat). Shared by FusedAdam and SelectiveAdam."""
    if len(state) == 0:
        state["step"] = torch.tensor(0.0, dtype=torch.float32)
        state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    m, v = state["exp_avg"], state["exp_avg_sq"]
    if not (m.is_contiguous() and v.is_contiguous() and m.dtype == v.dtype == torch.float32):
        raise RuntimeError(f"{who}: moments must be contiguous float32 like their parameter")
    state["step"] += 1
    return m, v


class FusedAdam(torch.optim.Adam):
    """``torch.optim.Adam`` with an exact fused CPU step (module docstring)."""

    def _plain(self) -> bool:
        for g in self.param_groups:
            if (g["amsgrad"] or g["weight_decay"] or g["maximize"] or g.get("differentiable")
                    or g.get("capturable") or g.get("fused") or isinstance(g["lr"], torch.Tensor)
                    or isinstance(g["betas"][0], torch.Tensor) or isinstance(g["betas"][1], torch.Tensor)):
                return False
            if any(p.grad is not None and not _supported(p) for p in g["params"]):
                return False
        return True

    @torch.no_grad()
    def step(self, closure=None):
        if not (ENABLED and self._plain() and exact()):
            return super().step(closure)
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        self._fused_step()
        return loss

    def _scratch_for(self, numel: int, one_pass: bool) -> torch.Tensor:
        """The kept float32 scratch :func:`_fused_update` needs for a parameter of ``numel``
        entries (grown when too small): a block per thread in one pass, else every square root."""
        need = min(numel, BLOCK) * (len(_thread_cuts(numel)) - 1) if one_pass else numel
        scratch = getattr(self, "_scratch", None)
        if scratch is None or scratch.numel() < need:
            scratch = self._scratch = torch.empty(need, dtype=torch.float32)
        return scratch

    @torch.no_grad()
    def _fused_step(self, one_pass: bool | None = None) -> None:
        if one_pass is None:
            one_pass = ONE_PASS and one_pass_exact()
        scratch = self._scratch_for(
            max((p.numel() for g in self.param_groups for p in g["params"] if p.grad is not None), default=0), one_pass)
        for g in self.param_groups:
            beta1, beta2 = g["betas"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                m, v = adam_moments(state, p, "FusedAdam")
                _fused_update(p, p.grad, m, v, float(state["step"].item()), float(g["lr"]), float(beta1),
                              float(beta2), float(g["eps"]), scratch, one_pass)


def warmup() -> float:
    """Compile (first run on a machine) or load the kernels and run the exactness check now."""
    import time

    t0 = time.perf_counter()
    exact()
    if one_pass_exact():  # the threaded pass (numba's parallel compile is the slow one)
        x = np.zeros(2 * BLOCK + 3, np.float32)
        f = np.float32(0.5)
        KERNELS.module.step_threads(x, x.copy(), x.copy(), x.copy(), f, f, f, f, f, f,
                                    np.empty((2, BLOCK), np.float32), BLOCK)
    return time.perf_counter() - t0
