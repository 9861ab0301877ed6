"""Beyond one machine: Ray runs many trainings (:mod:`.batch`) and splits a camera path's frames
over tasks (:mod:`.render_shards`).

Ray is optional: nothing here imports it at module level, and :func:`.ray_runtime.require_ray`
names the package to install when a command needs it. Captures and run folders are passed by
path, so on a cluster of several machines they sit on storage every node mounts at the same
path (as a render farm's shared storage).
"""
