"""The persistent JAX compilation cache, on by default, so a second run of the same configuration skips XLA.

Compiling the training loop of an MJX env takes tens of seconds on a CPU; the compiled executable only depends
on the program and the device, so it is written to disk and reused by every later process. The directory is
``$JAXROBO_CACHE_DIR`` if set, else ``~/.cache/jaxrobo/jax``; ``JAXROBO_CACHE_DIR=off`` (or ``0``, ``none``,
``false``, empty) turns it off. Call :func:`enable_compilation_cache` before the first compile of a process.
"""
from __future__ import annotations

import inspect
import os
from typing import Any

import jax

ENV_VAR = "JAXROBO_CACHE_DIR"
DEFAULT_DIR = os.path.join("~", ".cache", "jaxrobo", "jax")
_OFF = {"off", "0", "none", "false", "no", "disable", "disabled", ""}


def cache_dir(path: str | None = None) -> str | None:
    """The directory to use: ``path`` if given, else ``$JAXROBO_CACHE_DIR``, else the default; None when off."""
    value = path if path is not None else os.environ.get(ENV_VAR, DEFAULT_DIR)
    if value.strip().lower() in _OFF:
        return None
    return os.path.abspath(os.path.expanduser(value))


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn the persistent compilation cache on (every compile is cached, however small or quick).

    Returns the directory in use, or None when the cache is turned off (``path`` or ``$JAXROBO_CACHE_DIR`` set
    to ``off``). Raises ``OSError`` naming the directory if it cannot be created.
    """
    directory = cache_dir(path)
    if directory is None:
        return None
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as err:
        raise OSError(f"{ENV_VAR}={directory!r}: cannot create the compilation cache directory ({err})") from err
    jax.config.update("jax_compilation_cache_dir", directory)
    # JAX only caches compiles slower than 1 s and entries above a filesystem-dependent size by default; our
    # start-up is the sum of many small compiles (init, progress statistics, evaluation), so cache them all.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _reset_if_initialised()
    return directory


def entries(directory: str | None) -> int:
    """Number of files in a cache directory (a compile that adds none was served from the cache)."""
    if not directory or not os.path.isdir(directory):
        return 0
    return sum(len(files) for _, _, files in os.walk(directory))


def _reset_if_initialised() -> None:
    """JAX opens the cache at its first compile; if that already happened, make it reopen at the new path."""
    try:
        from jax._src import compilation_cache as cc

        if getattr(cc, "_cache_initialized", False):
            cc.reset_cache()
    except Exception:  # noqa: BLE001 - private API; without it the cache simply applies from the next process
        pass


# ---- traced programs: skip Python tracing too ----------------------------------------------------------------
_SOURCE_HASH: str | None = None


#: Packages whose sources :func:`source_hash` hashes: a traced program may be kept only if all its code comes from them.
OWN_PACKAGES = ("jaxrobo", "envs", "agents")


def source_hash() -> str:
    """Hash of jaxrobo's, the envs' and the agents' sources and assets: a traced program depends on all of them."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        import hashlib

        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        h = hashlib.sha256()
        for package in OWN_PACKAGES:
            for dirpath, dirnames, files in sorted(os.walk(os.path.join(root, package))):
                dirnames.sort()
                for name in sorted(files):
                    if name.endswith((".py", ".xml", ".yaml")):
                        with open(os.path.join(dirpath, name), "rb") as f:
                            h.update(name.encode() + f.read())
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


def _traced_library_versions() -> list[str]:
    """Versions of the physics libraries whose Python code a traced program inlines (MJX's step, Brax's
    pipelines): upgrading one must not reuse a program traced with the other."""
    from importlib import metadata

    out = []
    for dist in ("mujoco", "mujoco-mjx", "brax"):
        try:
            out.append(f"{dist}=={metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            out.append(f"{dist} absent")
    return out


def exported_jit(fn, example_args: tuple, out_like, tag: str, donate_argnums: tuple[int, ...] = (),
                 directory: str | None = None):
    """``jax.jit(fn)`` compiled for ``example_args``, whose traced program is kept on disk with ``jax.export``.

    The persistent compilation cache skips XLA, but a new process still traces ``fn`` in Python (for an MJX
    training chunk that is ~2-3 s of a CPU start-up). Here the first process serialises the traced program
    under ``<cache dir>/exported``; later ones load it and go straight to the (cached) compile. ``tag`` must
    name everything ``fn`` closes over (config, env options, discretiser, learner); the argument shapes, the
    sources of jaxrobo/envs/agents, the versions of JAX, MuJoCo, MJX and Brax, and the backend are added to
    the key. ``out_like`` is any pytree with the structure of the result (for ``run_chunk``: the runner).
    Without a cache directory or without the ``flatbuffers`` package this is a plain
    ``jax.jit(...).lower(...).compile()``.
    """
    import hashlib

    import jax.numpy as jnp

    directory = cache_dir(directory) if directory is not None else _current_dir()
    plain = lambda: jax.jit(fn, donate_argnums=donate_argnums).lower(*example_args).compile()  # noqa: E731
    try:
        from jax import export
        from jax._src.export import serialization  # noqa: F401  (needs flatbuffers)
    except ImportError:
        return plain()
    if directory is None:
        return plain()

    leaves, in_tree = jax.tree.flatten(example_args)
    leaves = [jnp.asarray(x) for x in leaves]
    is_key = [jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) for x in leaves]
    raw = [jax.random.key_data(x) if k else x for x, k in zip(leaves, is_key)]
    out_leaves, out_tree = jax.tree.flatten(out_like)
    out_key = [jax.dtypes.issubdtype(jnp.asarray(x).dtype, jax.dtypes.prng_key) for x in out_leaves]
    impls = [jax.random.key_impl(x) if k else None for x, k in zip(leaves, is_key)]
    donated = tuple(i for i, (arg_i, _) in enumerate(_leaf_owners(example_args)) if arg_i in donate_argnums)

    import re

    # MJX keeps static numpy arrays in the pytree metadata; their repr carries a memory address
    signature = re.sub(r" at 0x[0-9a-fA-F]+", "", repr([(x.shape, str(x.dtype)) for x in raw]) + str(in_tree)
                       + str(out_tree))
    key = hashlib.sha256("|".join([tag, signature, source_hash(), jax.__version__, jax.default_backend(),
                                   *_traced_library_versions()]).encode()).hexdigest()[:32]
    path = os.path.join(directory, "exported", f"{key}.bin")

    def flat(*xs):
        xs = [jax.random.wrap_key_data(x, impl=i) if k else x for x, k, i in zip(xs, is_key, impls)]
        out = fn(*jax.tree.unflatten(in_tree, xs))
        return [jax.random.key_data(y) if jax.dtypes.issubdtype(y.dtype, jax.dtypes.prng_key) else y
                for y in jax.tree.leaves(out)]

    exported = None
    if os.path.exists(path):
        try:
            with open(path, "rb") as f:
                exported = export.deserialize(bytearray(f.read()))
        except Exception:  # noqa: BLE001 - a stale or partial file is rebuilt
            exported = None
    if exported is None:
        try:
            exported = export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(x.shape, x.dtype) for x in raw])
            data = exported.serialize()
        except Exception:  # noqa: BLE001 - a program jax.export refuses (e.g. a custom call it cannot keep)
            return plain()
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
        exported = export.deserialize(data)  # compile what later processes will load: same cache entry
    try:
        compiled = jax.jit(exported.call, donate_argnums=donated).lower(*raw).compile()
    except Exception:  # noqa: BLE001 - a kept program this JAX cannot run: trace afresh (errors in fn surface there)
        return plain()
    out_impls = [jax.random.key_impl(jnp.asarray(x)) if k else None for x, k in zip(out_leaves, out_key)]

    def call(*args):
        xs = [jax.random.key_data(x) if k else jnp.asarray(x) for x, k in zip(jax.tree.leaves(args), is_key)]
        ys = compiled(*xs)
        ys = [jax.random.wrap_key_data(y, impl=i) if k else y for y, k, i in zip(ys, out_key, out_impls)]
        return jax.tree.unflatten(out_tree, ys)

    return call


def is_own_code(*objects: Any) -> bool:
    """True when every object's class (a function's own module, for functions) is defined in jaxrobo, envs or
    agents, whose sources key an exported program; code from elsewhere could change without the key changing."""
    for obj in objects:
        module = obj.__module__ if inspect.isfunction(obj) else type(obj).__module__
        if (module or "").split(".")[0] not in OWN_PACKAGES:
            return False
    return True


def _leaf_owners(args: tuple) -> list[tuple[int, int]]:
    """(argument index, leaf index) of every leaf of ``args``, in flattening order."""
    owners = []
    for i, a in enumerate(args):
        owners += [(i, j) for j in range(len(jax.tree.leaves(a)))]
    return owners


def _current_dir() -> str | None:
    """The compilation cache directory JAX is using (set by :func:`enable_compilation_cache`), if any."""
    value = jax.config.jax_compilation_cache_dir
    return value or None
