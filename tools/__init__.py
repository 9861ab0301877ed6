"""Development tools of BulletTime4D (benchmarks, stress suite, ablation, synthetic
captures, import-graph check): ``python -m tools <command>``. Not shipped with the
extension (``blender_manifest.toml`` excludes ``/tools/``). Imports ``engine``; the engine
never imports tools.
"""
