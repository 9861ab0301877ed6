"""Connecting to Ray: a cluster at an address, or a local instance on this machine.

One place decides how the engine meets Ray, so the batch and the sharded render behave alike:
Ray missing gets one line naming the package, an address nobody answers gets one line naming it
(checked with a plain TCP connect first: ``ray.init`` on a dead address retries for a minute).
"""
from __future__ import annotations

import os
import socket
import time
from pathlib import Path

RAY_PIN = "ray==2.60.0"  # the version CI installs and the README figures were measured with
CONNECT_TIMEOUT_S = 5.0


class ClusterError(RuntimeError):
    """Ray is missing, or the cluster cannot be reached; the message is one line for the user."""


def require_ray():
    """The ``ray`` module, or ClusterError saying how to install it (Ray is optional)."""
    try:
        import ray
    except ImportError as exc:
        raise ClusterError(f"this command needs Ray, an optional dependency: pip install {RAY_PIN}") from exc
    return ray


def split_address(address: str) -> tuple[str, int]:
    """``host:port`` (``ray://`` and ``http://`` prefixes allowed) -> (host, port); ValueError if not."""
    rest = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ClusterError(f"--address {address!r}: expected HOST:PORT, e.g. 10.0.0.5:6379")
    return host, int(port)


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """ClusterError naming ``address`` unless something accepts a TCP connection there."""
    host, port = split_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as exc:
        raise ClusterError(f"cannot reach the Ray cluster at {address}: {exc.strerror or exc} "
                           f"(is `ray start --head` running there?)") from exc


def connect(address: str | None = None, *, num_cpus: int | None = None, log_to_driver: bool = False):
    """Join the cluster at ``address``, or start a local Ray instance when it is None.

    Returns ``(ray, started_seconds)``. Already connected: reused as it is. A local instance gets a
    small object store (results are small: files go to shared storage, not through Ray)."""
    ray = require_ray()
    t0 = time.perf_counter()
    if ray.is_initialized():
        return ray, 0.0
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing may phone home
    kwargs = {"log_to_driver": log_to_driver, "include_dashboard": False, "configure_logging": True,
              "logging_level": "warning"}
    if address:
        check_reachable(address)
        if "RAY_AUTH_MODE" not in os.environ and _token_available():
            # `ray start --head` enables token authentication, but a client only sends the token
            # when told to: without this, joining a stock cluster fails with InvalidAuthToken
            os.environ["RAY_AUTH_MODE"] = "token"
        try:
            ray.init(address=address, **kwargs)
        except Exception as exc:  # Ray raises ConnectionError and others with pages of detail
            raise ClusterError(f"cannot join the Ray cluster at {address}: {str(exc).splitlines()[0]}") from exc
    else:
        ray.init(num_cpus=num_cpus, object_store_memory=200 * 1024 ** 2, **kwargs)
    return ray, time.perf_counter() - t0


def _token_available() -> bool:
    """Ray's token is where a client looks for it (env or ``~/.ray/auth_token``)."""
    if os.environ.get("RAY_AUTH_TOKEN"):
        return True
    path = os.environ.get("RAY_AUTH_TOKEN_PATH") or os.path.join(os.path.expanduser("~"), ".ray", "auth_token")
    return os.path.isfile(path)


def cluster_gpus(ray) -> float:
    """GPUs the connected cluster offers (0 when none)."""
    return float(ray.cluster_resources().get("GPU", 0.0))


def gpus_per_task(ray, wanted: float | None) -> float:
    """``wanted`` GPUs for each task, or by default one where the cluster has GPUs, else none."""
    if wanted is not None:
        return float(wanted)
    return 1.0 if cluster_gpus(ray) >= 1 else 0.0


def worker_env() -> dict:
    """Ray's runtime environment for our tasks: the engine from the path it has here (the same
    path on every node, like the captures), numba's cache where it already is."""
    root = str(Path(__file__).resolve().parents[2])
    paths = [root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p != root]
    return {"env_vars": {"PYTHONPATH": os.pathsep.join(paths)}}
