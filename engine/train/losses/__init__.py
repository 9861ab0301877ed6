"""The loss terms: ``LossTerm`` / ``StepContext`` and the frame terms (``terms``: L1 + D-SSIM,
Eq. 22; the block loss, Eq. 20; the stereo depth prior), the fused D-SSIM (``fused_ssim``) and the
two-view geometry terms and post-step hooks (``geometry_losses``).

May import: ``engine.train.config``, ``engine.train.frames`` and the packages below training."""
