"""numba's on-disk cache, one directory per import name of a module.

The engine's compiled code (the rasterizer kernels, the PNG row decoder) is cached with
``cache=True`` so that only the first process on a machine compiles it.
"""
from __future__ import annotations

import importlib
import os
import re
import threading


def install_cache_locator(module: str) -> None:
    """Give the numba functions of ``module`` (an import name) a cache directory of their
    own, keyed by that import name. Call it before the module's first ``njit(cache=True)``.

    numba's cache is keyed by source file, but a cache entry pickles the *import name* of
    the module. The same files are imported as ``engine.raster._kernels`` by
    ``python -m engine`` and as ``bl_ext.<repo>.bullettime4d.engine.raster._kernels``
    inside Blender; with one shared ``__pycache__`` the second one crashes loading the
    first one's entries (ModuleNotFoundError). The locator only answers for ``module``
    (other numba users in the process are untouched): ``$NUMBA_CACHE_DIR/bullettime4d``
    when set, else ``__pycache__`` next to the module's file, else ``~/.cache/bullettime4d``.
    """
    try:
        from numba.core import caching, config
        base = caching._CacheLocator
        mixin = caching._SourceFileBackedLocatorMixin
        impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
        impl._locator_classes.insert  # noqa: B018 - must be a list
    except (ImportError, AttributeError):  # a numba without these internals: default cache
        return
    tag = "numba-" + re.sub(r"[^A-Za-z0-9_.-]", "_", module)

    class PerImportNameLocator(mixin, base):
        def __init__(self, py_func, py_file, cache_path):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = cache_path

        def get_cache_path(self):
            return self._cache_path

        @classmethod
        def from_function(cls, py_func, py_file):
            if getattr(py_func, "__module__", None) != module or not os.path.exists(py_file):
                return None
            roots = []
            if config.CACHE_DIR:
                roots.append(os.path.join(config.CACHE_DIR, "bullettime4d"))
            roots.append(os.path.join(os.path.dirname(os.path.abspath(py_file)), "__pycache__"))
            xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
            roots.append(os.path.join(xdg, "bullettime4d"))
            for root in roots:
                self = cls(py_func, py_file, os.path.join(root, tag))
                try:
                    self.ensure_cache_path()
                except OSError:
                    continue
                return self
            return None

    impl._locator_classes = [c for c in impl._locator_classes
                             if getattr(c, "_bt4d_module", None) != module]
    PerImportNameLocator._bt4d_module = module
    impl._locator_classes.insert(0, PerImportNameLocator)




class LazyKernels:
    """A module of numba kernels, imported on first use (numba compiles or loads its cache
    then, seconds, so importing the engine stays cheap) and at most once across threads.
    ``load()`` returns the module or None; ``error`` holds why it could not be imported
    (no numba, a broken llvmlite), so a caller can fall back to its torch path and say why.
    """

    def __init__(self, package: str, name: str):
        self.package, self.name = package, name
        self.module = None
        self.error: BaseException | None = None
        self._lock = threading.Lock()

    def load(self):
        if self.module is None and self.error is None:
            with self._lock:
                if self.module is None and self.error is None:
                    try:
                        self.module = importlib.import_module("." + self.name, self.package)
                    except Exception as exc:  # ImportError, or a broken numba/llvmlite install
                        self.error = exc
        return self.module

    def available(self) -> bool:
        return self.load() is not None

    def unavailable_reason(self) -> str:
        self.load()
        return "" if self.error is None else f"{type(self.error).__name__}: {self.error}"
