"""``import mujoco.mjx`` without its mesh libraries: trimesh and scipy.spatial load when a model has a mesh.

MJX's mesh module (``mujoco.mjx._src.mesh``, imported by ``mujoco.mjx`` through its collision code) imports
``trimesh`` and ``scipy.spatial`` at its top, and they took most of the import of ``mujoco.mjx``: seconds of every
``jaxrobo train`` of an MJX task before its first compile. MJX calls them only to build the convex hulls of mesh
geoms (``mesh.convex``, ``mesh._convex_hull_2d``), which jaxrobo's robots do not have. :func:`import_mjx` imports
``mujoco.mjx`` with both deferred: while the mesh module is imported they are stand-ins in ``sys.modules`` (the
module reads ``trimesh.Trimesh`` in a function annotation as it is defined, nothing else of them), and afterwards
the mesh module's names for them import the real modules on first use; ``sys.modules`` is left without them, so
any other import of them is the usual one. A model with meshes loads them when MJX builds its hulls, as before.

It reaches into MJX's private mesh module, so it is guarded: it applies only to ``mujoco-mjx`` versions in
:data:`WRITTEN_FOR` whose mesh module imports exactly those names; elsewhere ``mujoco.mjx`` is imported as it is
(:func:`unavailable` says why). ``tests/test_mjx_import.py`` checks it on the installed version: nothing of trimesh
or scipy.spatial loaded after the import, a mesh model's hull the same as with the libraries loaded up front.

MJX also imports its optional Warp backend (``warp``, and the ``mujoco_warp`` it vendors) at its top where
``warp-lang`` is installed (MuJoCo Playground, in the ``bench`` extra, brings it): 1.1 s more import and 0.7 s
more exit for every command of an MJX task on 2 CPU cores, for a backend jaxrobo never selects. While
:func:`import_mjx` imports ``mujoco.mjx``, ``warp`` is kept out (``None`` in ``sys.modules``, which MJX reads as
not installed) unless it was imported already; afterwards an ``import warp`` is the usual one. So in a process
where jaxrobo imported MJX, MJX's Warp backend is off: a program that wants it imports ``mujoco.mjx`` (or
``warp``) itself before jaxrobo needs MJX. MJX prints two "Failed to import" lines where it finds no Warp;
:func:`import_mjx` drops exactly those lines (and writes any other output of the import).

Public surface: :func:`import_mjx`, :func:`unavailable`, :func:`installed_version`, :data:`WRITTEN_FOR`.
"""
from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import os
import re
import sys
import types
from typing import Any, Iterator

from jaxrobo.core.deferred import Deferred
from jaxrobo.core.version import installed, outside

#: The ``mujoco-mjx`` versions this was written and tested for: ``[low, high)`` as (major, minor).
WRITTEN_FOR = ((3, 17), (3, 18))
#: MJX's mesh module, and the top-level imports of it that are deferred.
_MESH = "mujoco.mjx._src.mesh"
_DEFERRED = ("trimesh", "scipy.spatial")


def installed_version() -> str | None:
    """The installed ``mujoco-mjx`` version string, or None if its metadata cannot be found."""
    return installed("mujoco-mjx")


#: :func:`unavailable`'s reason where this process has imported MJX's mesh module or its libraries already.
IMPORTED_ALREADY = "MJX's mesh module or its libraries are imported already"


def unavailable() -> str | None:
    """Why :func:`import_mjx` imports ``mujoco.mjx`` as it is (a sentence), or None when it defers the mesh
    libraries."""
    version = installed_version()
    reason = outside("mujoco-mjx", version, WRITTEN_FOR)
    if reason:
        return reason
    if any(name in sys.modules for name in _DEFERRED + (_MESH,)):
        return IMPORTED_ALREADY
    if "from scipy import spatial\nimport trimesh\n" not in _mesh_source() \
            or any(importlib.util.find_spec(name) is None for name in _DEFERRED):
        return f"mujoco-mjx {version}'s mesh module does not import trimesh and scipy.spatial as expected"
    return None


def _mesh_source() -> str:
    """The source of MJX's mesh module ("" where it is not found), read without importing ``mujoco.mjx`` (a spec
    of a submodule imports its packages, and ``mujoco.mjx``'s imports the mesh module)."""
    spec = importlib.util.find_spec("mujoco")
    for root in (spec.submodule_search_locations or []) if spec is not None else []:
        path = os.path.join(root, *_MESH.split(".")[1:]) + ".py"
        try:
            with open(path, encoding="utf-8") as f:
                return f.read()
        except OSError:
            continue
    return ""


class _StandIn(types.ModuleType):
    """A deferred module in ``sys.modules`` while MJX's mesh module is imported: ``Trimesh`` for the annotation
    it reads as it is defined; anything else raises, naming this module."""

    class Trimesh:  # the annotation's value only
        pass

    def __getattr__(self, attr: str) -> Any:
        raise AttributeError(f"jaxrobo.physics.mjx_import: {self.__name__}.{attr} used while mujoco.mjx was "
                             "imported")


#: What MJX prints on import where its optional Warp backend is not installed or kept out (jaxrobo does not use
#: it): two "Failed to import" lines on every command's output, though nothing failed that jaxrobo needs.
_NO_WARP = re.compile(r"Failed to import (mujoco_)?warp: (No module named '(warp|mujoco_warp)[\w.]*'"
                      r"|import of warp halted; None in sys\.modules)\n?")


@contextlib.contextmanager
def _quiet_about_warp() -> Iterator[None]:
    """Standard output of the block, less MJX's lines saying the optional Warp backend is not installed (any
    other line, a Warp that is installed but fails included, is written as it came)."""
    buffer = io.StringIO()
    try:
        with contextlib.redirect_stdout(buffer):
            yield
    finally:
        text = _NO_WARP.sub("", buffer.getvalue())
        if text:
            sys.stdout.write(text)


def import_mjx() -> types.ModuleType:
    """``mujoco.mjx``, imported with trimesh and scipy.spatial deferred and Warp kept out where :func:`unavailable`
    says None, and without MJX's lines saying its optional Warp backend is not installed."""
    if "mujoco.mjx" in sys.modules:
        return sys.modules["mujoco.mjx"]
    if unavailable() is not None:
        with _quiet_about_warp():
            return importlib.import_module("mujoco.mjx")
    names = {"trimesh": "trimesh", "scipy.spatial": "spatial"}  # the module, and the mesh module's name for it
    for name in names:
        sys.modules[name] = _StandIn(name)
    warp_kept_out = "warp" not in sys.modules
    if warp_kept_out:
        sys.modules["warp"] = None  # type: ignore[assignment]  # `import warp` raises ImportError: not installed
    try:
        with _quiet_about_warp():
            mjx = importlib.import_module("mujoco.mjx")
    finally:
        if warp_kept_out:
            del sys.modules["warp"]
        for name in names:
            del sys.modules[name]  # an import of them from now on is the real one
        mesh = sys.modules.get(_MESH)
        for name, attr in names.items():
            if mesh is not None and isinstance(getattr(mesh, attr, None), _StandIn):
                setattr(mesh, attr, Deferred(name))
    return mjx
