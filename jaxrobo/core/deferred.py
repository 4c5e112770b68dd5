"""A module imported on first use: :class:`Deferred`, the one stand-in both import tricks use
(:mod:`jaxrobo.physics.mjx_import` for MJX's mesh libraries, :mod:`jaxrobo.interop.deferred_imports` for Brax's
JAXopt and Orbax).

A :class:`Deferred` named ``name`` is a module object holding nothing: the first attribute anything reads of it
imports the real module, once, under a lock (trainers and compiles run in threads), and every attribute is then
the real module's. Where the stand-in itself is ``sys.modules[name]``, the import takes its place there (a later
``import name`` gets the real module); where the import fails, the stand-in stays and the next use tries again and
raises the import's own error.
"""
from __future__ import annotations

import importlib
import sys
import threading
import types
from typing import Any


class Deferred(types.ModuleType):
    """A stand-in for module ``name``: its first missing attribute imports the real module."""

    def __init__(self, name: str):
        super().__init__(name, f"{name} (deferred by jaxrobo: imported on first use)")
        self.__dict__["_jaxrobo_lock"] = threading.RLock()
        self.__dict__["_jaxrobo_module"] = None

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._jaxrobo_load(), attr)

    def _jaxrobo_load(self) -> types.ModuleType:
        with self._jaxrobo_lock:
            module = self.__dict__["_jaxrobo_module"]
            if module is None:
                placed = sys.modules.get(self.__name__) is self
                if placed:
                    del sys.modules[self.__name__]  # the import below finds and runs the real one
                try:
                    module = importlib.import_module(self.__name__)
                except BaseException:
                    if placed:
                        sys.modules.setdefault(self.__name__, self)  # a later use tries again, and says why
                    raise
                self.__dict__["_jaxrobo_module"] = module
            return module

    @property
    def loaded(self) -> bool:
        """Whether the real module has been imported through this stand-in."""
        return self.__dict__["_jaxrobo_module"] is not None
