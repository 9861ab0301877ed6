"""Training presets: one dataclass of hyper-parameters, three sizes for a 2-core CPU.

Schedules are expressed as *fractions of the total step count* so that a wall-clock budget
(``train(..., seconds=N)``) only has to pick a step count; everything else follows
deterministically from it. ``overrides`` (a dict) patches fields by name.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields


@dataclass
class TrainConfig:
    # ---- schedule -------------------------------------------------------------------
    iterations: int = 1000            # total optimisation steps (static + deformation)
    static_fraction: float = 0.3      # warm-up: canonical Gaussians only, no deformation
    static_frames: str = "first"      # warm-up on the first RGB instant ("first") or on every frame ("all")
    time_curriculum: float = 0.5      # fraction of the deformation stage over which frames are admitted in time order
    batch_views: int = 1              # views rendered per step
    expected_seconds: float = 90.0    # rough wall-clock on the demo capture, 2-core CPU
    # a --seconds budget plans at most this many x iterations steps (0: no cap) and ends early when the cap binds:
    # more steps overfit the two views (fast preset, 120 s budgets on a 2-core CPU ran 2700-7300 steps; at 2000
    # fixed steps eval PSNR was higher on 5 of 6 scene x model pairs, demo RGB-only 22.95 -> 24.25 dB; README, "eq16")
    budget_step_cap: float = 2.0

    # ---- initialisation -------------------------------------------------------------
    init: str = "auto"                # auto | ply | stereo (SGBM, fused) | planesweep | random
    init_max_points: int = 6000
    init_random_points: int = 3000
    init_fill_stride: int = 3         # stereo holes: points at interpolated depth every N px (0: random fill)

    # ---- Gaussians --------------------------------------------------------------------
    sh_degree: int = 0                # final SH degree (grown one band per sh_step_fraction)
    sh_step_fraction: float = 0.15
    lr_means: float = 1.6e-3          # x scene extent, decays exponentially to lr_means_final
    lr_means_final: float = 1.6e-5
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    init_opacity: float = 0.1
    # the Gaussians' optimizer: exact (FusedAdam, torch's Adam bit for bit) | selective (only the
    # rows visible in the step's renders and the curve columns its times read move; gsplat's
    # SelectiveAdam / Taming 3DGS, engine.scene.selective_adam). Not the default: 1000 fast steps,
    # seeds 0 / 1, demo / between / fast, moving pixels at the train views -0.43 / -0.16 / -0.31 dB
    # (eval views +0.22 / -0.03 / -0.12) for an RGB step 1.09x faster (README, Selective Adam)
    # | lazy (the curves' touched columns, each caught up on the steps it skipped, and a render's
    # columns before it reads them: dense Adam to rounding but for the inner-residual prior on untouched
    # columns; engine.scene.lazy_adam) | auto (lazy for curves of at least lazy_min_columns columns, and
    # for every curve under lazy_rgb_only; FusedAdam otherwise: README, "Lazy curve Adam")
    gaussian_adam: str = "auto"
    # gaussian_adam=auto: curves of at least this many control-point columns (K = 3 (F - 1) + 1 for F
    # RGB instants) take the lazy step (engine.scene.lazy_adam), shorter ones FusedAdam's
    lazy_min_columns: int = 40
    # ... and every curve in an RGB-only run whose every frame is an RGB instant: its renders never read
    # the inner columns, so with the read catch-up the lazy step is dense Adam to rounding (README,
    # "Lazy curve Adam, reads caught up")
    lazy_rgb_only: bool = True

    # ---- densification (3DGS rules, schedule in fractions of `iterations`) ---------------
    densify_from: float = 0.05
    densify_until: float = 0.7
    densify_every: int = 100          # steps
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01       # clone if max scale <= this * extent, else split
    prune_opacity: float = 0.005
    prune_big_world: float = 0.2      # prune if max scale > this * extent
    opacity_reset_every: int = 0      # steps, 0 = never (short CPU schedules)
    max_gaussians: int = 20000

    # ---- deformation (HexPlane + MLP, paper Eq. 1, 5) ----------------------------------
    hex_resolution: int = 24          # base spatial resolution of each plane axis
    hex_multires: tuple = (1, 2)      # resolution multipliers
    hex_features: int = 16            # channels per plane
    time_resolution_per_frame: float = 1.0  # time cells = ceil(rgb instants * this) + 1
    mlp_width: int = 64
    mlp_depth: int = 1                # hidden layers of phi_d
    deform_scale: bool = False        # DynTCG: no scale deformation unless it pays
    deform_opacity: bool = False
    deform_color: bool = False
    lr_grid: float = 5e-2
    lr_grid_final: float = 1.6e-3
    lr_mlp: float = 5e-3
    lr_mlp_final: float = 1.6e-4
    tv_weight: float = 2e-4           # spatial plane total variation
    time_smooth_weight: float = 1e-3  # second difference along t of the time planes
    time_l1_weight: float = 1e-4      # time planes close to 1 (static by default)

    # ---- motion representation (issue 11; engine.scene.trajectory) --------------------------
    # trajectory (default since this round): per-Gaussian cubic Bezier curves through the RGB instants.
    # 1000 fast steps, RGB-only, eval cameras, all frames, hexplane -> trajectory (README "Motion
    # representation"): demo 20.36 -> 21.55, novel 21.92 -> 23.17, between 20.05 -> 20.59, fast
    # 20.31 -> 20.21 dB; moving pixels at the train views 18.4 -> 32.6 / 25.0 -> 35.4 / 20.1 -> 39.4 / 20.3 -> 26.1
    motion: str = "trajectory"        # hexplane | trajectory | trajectory+hexplane (HexPlane as a residual)
    lr_traj: float = 1.6e-3           # x extent: per-Gaussian trajectory control points, decays to lr_traj_final
    lr_traj_final: float = 1.6e-5
    lr_traj_quats: float = 1e-3       # quaternion residual curve
    traj_carry: str = "flow"          # admitted RGB instants start from: flow (stereo + optical flow) | velocity | hold
    # x extent: with traj_carry=flow, hidden Gaussians take the motion of the nearest carried /
    # still one within this distance (0: off)
    traj_carry_hidden: float = 0.05
    traj_carry_flow: str = "lk"       # optical flow of the carry: lk (engine.train.interpolation) | dis (OpenCV DIS)
    traj_carry_fb: float = 0.0        # px: forward-backward flow check of the carry (0: off; scene_flow.carry_by_flow)
    # births (engine.train.births): at each admitted RGB instant, new Gaussians with a temporal
    # opacity where the render still misses the frame by more than this (max channel; 0: off)
    # (0.15: fast scene moving pixels at the train views 25.8 -> 33.4 dB, eval +0.55 dB at equal
    # steps, +1.0 at equal time; README "Births")
    birth_error: float = 0.15
    birth_stride: int = 2             # px between candidate pixels
    birth_max: int = 2000             # most Gaussians born per frame
    birth_lifespan: float = 0.5       # temporal std at birth, x the RGB frame interval
    birth_opacity: float = 0.5
    # temporal std (x the frame interval) of born Gaussians whose pixel's colour a neighbouring RGB
    # instant repeats (births.unchanged_pixels: a static surface, which should not fade; an
    # occluder in front hides it); 0: off, every born Gaussian gets birth_lifespan. With
    # birth_depth_guard 0.8, 1000 fast steps, seeds 0 / 1, eval between RGB instants against both
    # off (main edd3ac0): fast +0.24 / +0.31 dB, demo +0.20 / +0.14, between -0.02 / +0.04; at the
    # RGB instants fast +0.26 / +0.40 (README "Births at a wrong stereo depth")
    birth_static_lifespan: float = 16.0
    # no birth at such a pixel where its stereo depth is less than this x the render's depth and
    # the render is opaque there (births.stereo_in_front): the model has the surface, the stereo
    # match is what is wrong (periodic texture, low resolution), and the born Gaussian would float
    # in front of it at other viewpoints, for birth_static_lifespan; 0: off. Stereo / render depth
    # of static births: fast and demo median 1.00-1.05, 1-12 % below 0.8; the 32x24 capture of
    # tests/test_train.py median 0.73, 70-80 % below 0.8 (eval 24.29 -> 27.94 with the lifespan on)
    birth_depth_guard: float = 0.8
    # born Gaussians' motion before their instant: none (static curve) | lk / dis (the train
    # cameras' optical flow T_j -> T_j-1 by that method + stereo) | nearest (the nearest alive
    # Gaussian's) | match (component_flow: one translation per born region); births.py
    birth_motion: str = "none"
    birth_match_radius: float = 0.25  # x image width: search radius of birth_motion=match
    traj_inner_weight: float = 1.0    # mean squared inner-point residual / extent^2 (between-frame losses move them)
    rigidity_weight: float = 0.0      # Luiten et al. local rigidity (rigid + rot + iso over kNN) / extent; 0: off
    rigidity_k: int = 8               # neighbours of the rigidity prior

    # ---- loss -------------------------------------------------------------------------
    lambda_dssim: float = 0.2
    lambda_block: float = 0.5         # L1 of 4x4 average-pooled images (paper Eq. 20 block loss)
    block_size: int = 4
    lambda_depth: float = 0.1         # relative L1 to fused SGBM stereo depth at every RGB instant (issue 14)
    depth_prior_planes: bool = False  # lambda_depth also where stereo is empty, on the dominant planes
    #                                   (novel depth error at 20 deg 1.6 -> 1.3 %, but -0.56 dB; demo -0.06: off)
    background: tuple = (0.0, 0.0, 0.0)

    # ---- two-view geometry (issue 14, engine.train.geometry_losses; README "Two-view geometry") ----
    # measured at 600 fast steps (equal cost per step): lambda_depth alone pays (novel scene
    # 19.70 -> 20.72 dB, median depth error at 20 deg 10.7 -> 4.4 %) and is on (above); these
    # three on top of it cost 0.4 dB there (20.34 dB; binocular alone 19.65), so they are off.
    lambda_binocular: float = 0.0     # L1 of the partner view warped through the rendered depth (Binocular3DGS: 0.5)
    lambda_depth_smooth: float = 0.0  # edge-aware smoothness of the rendered depth (measured: 0.05)
    # x opacity of the Gaussians a step sees (Binocular3DGS: 0.995); 1 = off. It acts from
    # opacity_decay_from until opacity_decay_until (fractions of the schedule; None: densify_until,
    # the end of densification, 0.7), whose opacity prune removes the Gaussians it fades; after it opacities recover
    # under the photometric loss alone. 1000 fast steps, full model, seeds 0 / 1, eval all frames, on
    # minus off: novel +0.44 / +0.10, between +0.06 / +0.45, demo -0.14 / +0.54, fast -0.08 / -0.11 dB,
    # LPIPS lower on all eight runs; decaying to the end costs fast -0.33 / -0.36 and demo -0.41 /
    # +0.22. It removes `between`'s more-steps-worse overfit (holes in the floor at the eval cameras;
    # README "More steps, worse novel views")
    opacity_decay: float = 0.995
    opacity_decay_from: float = 0.0
    opacity_decay_until: float | None = None  # None: densify_until (opacity_decay_window)
    # cracks at a virtual view cover_angle_deg off the step's frame (geometry_losses.cover_loss); 0: off.
    # 1000 fast steps, full model, eval all frames, off -> 0.5, seeds 0 / 1: between 21.67 / 21.58 ->
    # 23.99 / 24.20 dB, demo 22.07 / 22.05 -> 24.21 / 23.87, fast 20.99 / 21.35 -> 22.58 / 22.64, novel
    # 23.93 / 23.81 -> 25.01 / 25.01; LPIPS lower on all eight; RGB-only s0 between 20.64 -> 22.65, demo
    # 21.54 -> 24.25; 2.0 (first version): between s0 23.53. Equal time 120 s, full model, between RGB
    # frames: +0.8 to +2.2 dB on six runs. README "No cracks at a new viewpoint"
    lambda_cover: float = 0.5
    cover_angle_deg: float = 20.0
    # steps between virtual renders. 4 against 2, 1000 fast steps, full model, all frames, seeds 0 / 1:
    # between +0.26 / +0.04 dB, demo -0.02 / +0.41, fast -0.07 / +0.05, novel +0.09 / +0.06; 320x240 demo
    # (RGB-only) +0.24 / +0.66; an RGB step 13 % cheaper in CPU time, a guided one 7 % (README "Every
    # fourth step"); 1: between -0.02, 320x240 demo -0.16
    cover_every: int = 4
    cover_scale: float = 0.5          # virtual render's resolution, x the frame's
    # closing box that tells cracks from the outline, x the virtual render's shorter side (odd px,
    # geometry_losses.cover_kernel_px): 9 px on the test scenes (80x60, 96x72 renders), 45 at 1080x720
    cover_kernel_frac: float = 0.125
    # attributes the term trains: all | "+"-joined of means, quats, scales, size, opacities, colors.
    # opacities+means (no shape change): 320x240 demo +1.2 / +2.0 dB, LPIPS 0.22 -> 0.13 (no streaks
    # along the train rays on its brick wall); but 320x240 `between` -0.53, 160x120 scenes -0.6 to +0.2
    # (holes left in the floor): all (README "What the term may change")
    cover_grad: str = "all"
    random_background: bool = False   # random background per step (with init_backdrop 0.3: demo -1.7 dB, off)
    init_backdrop: float = 0.3        # points beyond each image border (this fraction wide) on the dominant planes
    init_planes: bool = True          # stereo holes take the dominant planes' depth where it agrees (geometry.planes)
    backdrop_opacity: float = 0.9     # opacity of the init_backdrop Gaussians at step 0 (no view trains them); 0: off
    # (all three act only with stereo init; a points.ply init has no backdrop.) Measured at 600 fast steps
    # with the backdrop left out of the scene extent and the field bounds (Trainer.field_box): novel scene
    # (RGB-only) 22.79 -> 23.53 dB, coverage at 20 deg 95.2 -> 100 %, depth error 2.5 -> 1.7 %; demo
    # (filled eval, same session) -0.02 / +0.10 dB on seeds 0 / 1 (RGB-only +0.07 / -0.21). Before that
    # fix, RGB-only in an earlier session: demo -0.17 / -0.67. README "The backdrop no longer widens".

    # ---- bookkeeping ------------------------------------------------------------------
    checkpoint_every_s: float = 30.0
    log_every: int = 1

    # ---- skipping: what a scene does not need; switches of the trainer (engine.train) ---
    freeze_static: bool = False           # CPOStream freezing: Gaussians quiet for K checks skip the deformation field
    freeze_k_checks: int = 3              # K: consecutive quiet checks before a Gaussian freezes
    freeze_motion_eps_px: float = 0.3     # quiet: motion over the train frame times <= this (px, train cameras)
    freeze_wake_residual: float = 0.15    # observation module: a frozen Gaussian under a larger residual wakes
    freeze_checks_per_stage: int = 20     # motion checks spread over the deformation stage
    freeze_start_fraction: float = 0.3    # first check after this fraction of the deformation stage
    early_stop: bool = False              # stop when the held-out proxy PSNR stops improving
    early_stop_patience: int = 3          # proxy evaluations without a gain before stopping
    early_stop_min_delta: float = 0.05    # dB: a smaller gain is no gain
    early_stop_every_fraction: float = 0.05  # proxy evaluation every this fraction of the steps
    early_stop_min_deform_fraction: float = 0.25  # never stop before this fraction of the deformation stage
    early_stop_proxy_frames: int = 4      # eval frames of the proxy (train frames when the capture has none)
    cull_frustum: bool = False            # prune Gaussians outside every train frustum (start, stage change, densify)

    # ---- spike guidance (BulletTime4D, engine.train.spike_guidance; ignored with rgb_only) ------
    fine_deformation: bool = True  # Eq. 6-10 fine spike feature added to the HexPlane feature
    fine_per_gaussian: bool = False  # per-Gaussian spike features (else one per instant)
    # conv texture encoder frozen at its random init: each spike window is encoded once per run
    # (EncodedWindows). Measured (README, Spike guidance), demo, 600 fast steps, eval between frames /
    # moving px, seeds 0 / 1: trained 19.78 / 15.36, 20.06 / 17.63 -> frozen 20.04 / 15.65, 20.30 / 17.63
    fine_frozen_encoder: bool = True
    fine_k_sub: int = 8  # sub-windows (attention tokens) per RGB interval
    fine_d_model: int = 64  # attention width of the fine branch
    fine_channels: int = 32  # conv channels of the spike texture encoder
    lr_fine: float = 1e-3  # learning rate of the fine branch
    # spike windows' conv encoder output kept (EncodedWindows, issue 13): 1 = one pass per window
    # and weights (renders of a step share it; exact), k > 1 = a window's encoder runs, forward and
    # backward, at most every k steps, its tokens reused detached in between; 0 = no reuse
    fine_encoder_every: int = 1
    spike_loss_weight: float = 1.0  # Eq. 17 (rate L1 in linear-luminance units)
    spike_window: int = 32  # m: spike frames per rendered window (paper: 32)
    spike_loss_mode: str = "counts"  # counts (expected counts) | if (m-step IF, surrogate gradient)
    # Eq. 20 block colour loss at between-frame instants against the frame interpolated from the
    # RGB frames. With trajectories it is off: where the motion is not smooth at 30 FPS the
    # interpolated frame contradicts the spike stream (1000 fast steps, with -> without: ``between``
    # scene 20.77 -> 21.13 dB, demo 20.82 -> 20.97, fast 19.91 -> 19.90, novel 23.56 -> 23.48); the
    # HexPlane field needs it (demo 20.91 -> 20.25). README "Spike guidance".
    block_loss_weight: float | None = None  # None: 1.0 with the HexPlane field alone, else 0 (block_weight)
    block_interp: str = "flow"  # flow | linear (RIFE stand-ins)
    # a between-frame render every k deformation steps (0: never); k = 2 brings the guided step under
    # 1.6x the RGB step but lost 1.5 dB on moving pixels on one of two demo seeds (README): 1
    between_every: int = 1
    between_colocated_p: float = 0.75  # share of between renders at the spike camera's view
    between_scale: float = 0.5  # between-frame renders at this fraction of the RGB resolution
    spike_time_resolution_per_frame: float = 6.0  # HexPlane time cells per RGB frame with guidance
    # time_smooth_weight with guidance (its finer time cells see one view between frames)
    spike_time_smooth_weight: float = 0.1
    between_curriculum: bool = True  # between-frame instants only up to the time curriculum's front
    # between-frame losses train the deformation field only (measured: worse between frames)
    between_motion_only: bool = False
    spike_static_prior: bool = True  # Gaussians where the spike view never changes skip the deformation field
    spike_skip_static: bool = True  # no between-frame renders in spike windows without change (engine.spike.change)
    fine_change_gate: bool = True  # fine feature only for Gaussians where / windows when the spike view changes
    spike_change_block: int = 4  # block size (spike pixels) of the change maps
    # the spike loss's between-frame render only over the box where its interval's spike view changes
    # (engine.train.spike_crop; full view when the box exceeds spike_crop_max_frac of it). Off: ~3 % of a
    # guided step saved; 1000 fast steps, seeds 0 / 1, between frames demo +0.57 / +0.24 dB, fast -0.06 / -0.11,
    # between +0.09 / -0.26 (at RGB instants fast -0.19 / -0.24, between +0.10 / -0.29)
    spike_crop: bool = False
    spike_crop_dilate: int = 1  # change-map blocks added around the changed ones
    spike_crop_max_frac: float = 0.8
    # along-ray prior (issue 11, engine.train.along_ray): between RGB instants the distance of the
    # Gaussians the spike loss touches from the spike camera follows a smooth curve through its
    # values at the neighbouring RGB instants (the one component the spike view cannot see)
    lambda_along_ray: float = 0.0  # weight of the prior (0: off)
    along_ray_curve: str = "hermite"  # hermite (Catmull-Rom tangents) | linear
    along_ray_beta: float = 0.01  # smooth-L1 knee, x extent
    along_ray_max_gaussians: int = 4096  # random subset of the touched Gaussians per step (0: all)
    # local rigidity between RGB instants (issue 11, engine.train.between_rigidity): at each between-frame
    # render's instant the Gaussians that move over its RGB interval keep Luiten et al.'s rigidity, rotation
    # similarity and isometry over rigidity_k neighbours with respect to both ends of the interval. Off:
    # 1000 fast steps, eval between RGB frames, fast +0.04 / +0.13 dB (moving pixels +0.01 / -0.01),
    # between -0.01, ~1.6x the run's time (README "The fast scene's ghost")
    rigidity_between_weight: float = 0.0  # 0: off (the term is not built)
    rigidity_between_min_move: float = 0.005  # moving: displaced over the interval by more than this x extent
    rigidity_between_every: int = 100  # steps an interval's neighbour lists are reused (same Gaussian set)
    rigidity_between_max_gaussians: int = 8192  # random subset of the moving Gaussians (0: all)
    # spike-view optical flow (issue 11, engine.train.spike_flow): the visible Gaussians' projected
    # displacement at the spike camera from an RGB instant to a between instant follows the flow
    # between grey images reconstructed from the spikes (trajectories only)
    # on: 1000 fast steps, eval cameras between RGB frames vs the spike loss alone (seeds 0 / 1): between
    # +0.69 / +0.44 dB (moving pixels +1.39 / +1.26), demo +0.14 / +0.18, fast +0.28 / +0.14, novel -0.02 / +0.56
    spike_flow_weight: float = 1.0  # 0: off (the term is not built)
    spike_flow_window: int = 128  # TFP window (spike frames) of the grey images (EPE vs window: README)
    spike_flow_steps: int = 15  # between instants per RGB interval with a cached flow
    spike_flow_fb_tol: float = 0.5  # forward-backward consistency tolerance (spike px, + 10 % of |flow|)
    # each grid instant's flow starts from the one a step closer to its RGB instant (spike_flow_pairs): on
    # the fast scene's ball the far half-interval's error 14.6 -> 5.8 px (motion 16-17 px); False: from zero.
    # 1000 fast steps, seeds 0 / 1 / 2, eval between RGB frames: fast +0.47 / +0.50, between +0.01 / -0.17 /
    # +0.10, demo +0.16 / -0.04 / +0.19 dB (README "The spike flow lost the ball too")
    spike_flow_warm: bool = True
    spike_flow_depth_tol: float = 0.03  # visible surface: |z - rendered depth| <= tol x depth
    spike_flow_beta: float = 1.0  # smooth-L1 knee (spike px)
    spike_flow_max_gaussians: int = 4096  # random subset of the surface Gaussians per step (0: all)
    # DIS runs on the grey images upsampled this many times. 1 (at the sensor's pixels) would save ~3 ms of a
    # guided demo step, but its flows are worse (EPE on the fast ball 5.8 -> 6.4 px, ``between``'s ball 1.4 -> 1.7)
    # and 1000 fast steps lose between RGB frames on all six runs: demo -0.09 / -0.05, fast -0.29 / -0.49,
    # between -0.21 / -0.22 dB (README "The guided step's per-run work")
    spike_flow_upsample: int = 2
    # steps a reference instant's visible-surface set (a render at the spike view, ~11 ms) is reused while the
    # Gaussian count is unchanged; 10 -> 30: 1000 fast steps, seeds 0 / 1, between RGB frames demo +0.12 / +0.02,
    # fast +0.01 / -0.04, between -0.03 / -0.07 dB (README "The guided step's per-run work")
    spike_flow_surface_every: int = 30
    # RGB intervals beyond the admitted time whose flows a background thread computes ahead of the steps that
    # need them (engine.train.spike_flow_cache; the same flows): 0 computes each in the step that first needs it
    spike_flow_prefetch: int = 2
    spike_flow_fit: bool = True  # once per interval, least-squares fit of the inner control points to the flow
    spike_flow_min_px: float = 0.5  # the fit leaves curves whose median flow is below this (spike px) where they are
    # the curves' place at the next RGB instant from the spike flow (spike_flow.flow_junctions), at each
    # interval's fit: "all" the surface Gaussians at the left end; "born" only those born at either end (each
    # to the other end); "none". all: 1000 fast steps, seeds 0 / 1, eval between RGB frames: fast +0.19 / +0.20,
    # between -0.02 / +0.02, demo -0.00 / +0.13 dB (README "The fast scene's ghost")
    spike_flow_junctions: str = "all"
    # with it, the Gaussians the spike view does not see (a moved part's back and inside) take the change of
    # the nearest moved one within traj_carry_hidden x extent. On (with spike_flow_warm): 1000 fast steps,
    # seeds 0 / 1 / 2, eval between RGB frames against warm flows alone: fast +0.23 / +0.32, between -0.06 /
    # +0.04 / -0.15, demo +0.01 / -0.11 / +0.07 dB (README "The spike flow lost the ball too")
    spike_flow_junctions_hidden: bool = True
    # quiet curves (issue 11, engine.train.quiet_curves): segment k's inner control points stay at zero
    # (the Catmull-Rom curve) for Gaussians that project at both of its RGB instants where the spike view
    # saw no change in interval k (dilated by quiet_curves_dilate change-map blocks). On: 1000 fast steps,
    # seeds 0 / 1, full - RGB-only between RGB frames at the eval cameras, off -> on: demo -0.24 / -0.27 ->
    # +0.30 / +0.24 dB, fast +0.13 / +0.11 -> +0.20 / +0.43, between +1.53 / +1.26 -> +1.47 / +1.38
    # (README "Quiet curves"); dilation 2 / 1 / 0 blocks, post hoc: demo 21.74 / 21.95 / 22.05 dB,
    # between 21.80 / 21.83 / 21.69 (0 clips the moving objects' edges)
    quiet_curves: bool = True
    quiet_curves_dilate: int = 1
    # steps a quiet mask (~14 ms at 23k Gaussians) is reused while the Gaussian count is unchanged; 10 -> 50:
    # 1000 fast steps, seeds 0 / 1, between RGB frames demo +0.06 / +0.22, fast +0.05 / +0.04, between
    # +0.02 / -0.06 dB (README "The guided step's per-run work")
    quiet_curves_refresh: int = 50
    # quiet_junctions: the junctions joined by quiet segments are also held equal (their mean): a Gaussian
    # the spike view saw still over a run of RGB intervals stays where it was. Off: 1000 fast steps, seeds
    # 0 / 1 / 2, between RGB frames: demo +0.13 / +0.27 / -0.05, fast +0.26 / +0.05, between -0.13 / -0.14 /
    # -0.06 dB (README "Where the demo loses to the Interpolate baseline")
    quiet_junctions: bool = False
    # still hold (issue 11, engine.train.still_hold): every still_every-th deformation step also renders
    # a train camera at a random instant between two of its RGB frames; its loss counts only where the
    # two frames agree and nothing passed through (the still background), target their linear blend.
    # Off: it holds the demo's still background half-way between RGB instants (RGB-only 25.63 -> 25.88 dB,
    # full 25.32 -> 25.35, with quiet_junctions 25.62) but 1000 fast steps, between RGB frames, move within
    # noise: full fast -0.02, between -0.03, demo -0.03; with quiet_junctions demo +0.18 / +0.31 / -0.07,
    # between -0.01 / -0.07 / -0.14, fast +0.20 / +0.00; RGB-only +0.04 / +0.01 / +0.06 (README "Still frames
    # held between the RGB instants"); an extra render every still_every steps
    still_weight: float = 0.0  # 0: off (the term is not built)
    still_every: int = 2
    still_colour_tol: float = 0.015  # changed: 3 x 3 box means differ by more than this in any channel
    still_margin_px: int = 2  # the changed and swept pixels dilated by this
    still_spike_dilate: int = 1  # full model: pixels over spike blocks changed in the interval (dilated) are not still
    baseline: str = ""  # training-data variant: repeat | interp-linear | interp-flow | spike2img
    baseline_per_interval: int = 9  # synthetic frames per RGB interval (30 -> 300 FPS)
    # how the full model (and the baselines) treat the synthetic frames (issue 11, engine.train.baselines):
    # "all": their instants are RGB instants too (trajectory knots, scene-flow carries, births, the spike
    # branch's intervals) -- paper Table 1's "train on them as if they were real"; "real": knots and the
    # spike branch stay at the capture's RGB instants and the synthetic frames only supervise the curves
    # between them (a frame loss at between-frame instants, like the spike loss). 120 s, seed 0, full + interp,
    # between frames: between 18.82 -> 19.93 dB, demo 16.12 -> 21.89 (all: 130 / 84 steps, real: 506 / 541).
    # "all" stays the default: it is the Table 1 baseline's definition (README "Flow-interpolated frames
    # in the full model"; none of these is on in the full model: it loses on `between`, -0.74 / -1.16 dB)
    baseline_instants: str = "all"
    # frame-loss weight (L1, D-SSIM, block L1) of a synthetic frame; 0.5: demo 21.82 -> 21.76, between 20.45 -> 20.33
    baseline_weight: float = 1.0
    # > 0: synthetic pixels where both source flows fail the forward-backward check by more than this
    # many pixels (at the sampled location) carry no frame loss (the render is its own target there);
    # 1 px with "real", seed 0: demo 21.82 -> 22.28, between 20.45 -> 20.37, fast 20.51 -> 20.47 dB
    baseline_mask_px: float = 0.0

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        names = {f.name: f for f in fields(cls)}
        kwargs = {}
        for k, v in d.items():
            if k not in names:
                continue
            if isinstance(names[k].default, tuple) and isinstance(v, list):
                v = tuple(v)
            kwargs[k] = v
        return cls(**kwargs)

    def replace(self, **changes) -> "TrainConfig":
        return apply_overrides(self, changes)


def _fast() -> TrainConfig:
    return TrainConfig()


def _balanced() -> TrainConfig:
    # fast's deformation field (HexPlane 24, MLP 64): with HexPlane 32 / MLP 96 this preset
    # collapsed on the demo (16.92 dB, train views 23.3 dB); with the small field it scores
    # 20.44 dB (README, Benchmarks). More steps and Gaussians are what two views can use.
    # budget_step_cap 1.5 (3750 steps): at 5000 (the cap of 2) LPIPS was worse on both scenes (demo 0.078 ->
    # 0.090, between 0.109 -> 0.118) for +0.06-0.17 dB; at 3750 0.081 / 0.110 and 24.23 / 24.31 dB against
    # 23.99 / 24.35 at 2500 (seed 0, full model; README "The step cap")
    return TrainConfig(
        iterations=2500, expected_seconds=420.0, sh_degree=1, init_max_points=10000,
        densify_every=100, max_gaussians=30000, hex_resolution=24, mlp_width=64,
        checkpoint_every_s=60.0, budget_step_cap=1.5,
    )


def _quality() -> TrainConfig:
    # Retuned (README, Benchmarks): the old 6000 steps / SH 2 / 50k / HexPlane 48x24 / MLP 128
    # never finished in its budget, and its big deformation field fitted each instant's two
    # views by warping the static scene (train-view 33 dB, -9.4 dB without the field) until
    # training collapsed (train-view 14 dB at step 4099 of 6000; held-out 14.6 dB at 4390).
    # "More" is now steps and Gaussians; with balanced's field (32x16, MLP 96) it scored 19.55 dB
    # (fast 19.70, within noise). The same field collapsed once in balanced (16.9 dB): not fully fixed.
    # budget_step_cap 1: a budget never runs it past its own 3000 steps. At 6000 (what the cap of 2 let a
    # 600 s budget plan) it overfits: demo 23.81 -> 23.36 dB, LPIPS 0.083 -> 0.104; between 24.37 -> 24.21,
    # 0.108 -> 0.121 (seed 0, full model; README "The step cap").
    return TrainConfig(
        iterations=3000, expected_seconds=750.0, sh_degree=1, init_max_points=12000,
        densify_every=150, max_gaussians=40000, hex_resolution=32, hex_features=16, mlp_width=96,
        checkpoint_every_s=120.0, budget_step_cap=1.0,
    )


PRESETS = {"fast": _fast, "balanced": _balanced, "quality": _quality}


def block_weight(cfg: TrainConfig) -> float:
    """The block colour loss's weight (Eq. 20): ``cfg.block_loss_weight``, or when it is None
    1.0 for the HexPlane field alone and 0 for per-Gaussian trajectories (measured, above)."""
    if cfg.block_loss_weight is not None:
        return float(cfg.block_loss_weight)
    return 1.0 if cfg.motion == "hexplane" else 0.0


def opacity_decay_window(cfg: TrainConfig) -> tuple[float, float]:
    """(from, until) of the opacity decay as fractions of the schedule: ``opacity_decay_until``,
    or when it is None ``densify_until``, so the decay ends where densification's opacity prune
    does whatever the densification window is set to."""
    until = getattr(cfg, "opacity_decay_until", None)
    if until is None:
        until = getattr(cfg, "densify_until", 1.0)
    return float(getattr(cfg, "opacity_decay_from", 0.0)), float(until)


def apply_overrides(cfg: TrainConfig, overrides: dict | None) -> TrainConfig:
    """A copy of ``cfg`` with fields replaced; unknown names raise ``KeyError``."""
    if not overrides:
        return dataclasses.replace(cfg)
    names = {f.name: f for f in fields(TrainConfig)}
    changes = {}
    for k, v in overrides.items():
        if k not in names:
            raise KeyError(f"unknown training option {k!r}; known: {', '.join(sorted(names))}")
        default = names[k].default
        if isinstance(default, tuple) and isinstance(v, list):
            v = tuple(v)
        elif isinstance(default, bool):
            v = bool(v)
        elif isinstance(default, int) and not isinstance(default, bool):
            v = int(v)
        elif isinstance(default, float) or (default is None and v is not None
                                            and names[k].type == "float | None"):
            v = float(v)  # an optional float (None: decided by other fields) given a value
        changes[k] = v
    return dataclasses.replace(cfg, **changes)


def get_preset(name: str = "fast", overrides: dict | None = None) -> TrainConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return apply_overrides(PRESETS[name](), overrides)
