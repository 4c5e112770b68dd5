"""Traced programs kept across processes, so that a warm start skips tracing as well as XLA.

The persistent compilation cache (:mod:`jaxrobo.speed.cache`) serves XLA's output, but it is keyed on the lowered
module, so every process still traces and lowers its programs in Python before it can look one up. On an H200
host that was most of a warm default run's compile (JAX's compile log, warm cache): Goto-v2 traced its training
chunk for 2.8 s and its greedy evaluation for 1.1 s of a 4.4 s compile, ArmReach-v0 3.1 s and 3.6 s of 5.3 s.

Where the execution plan says so (``ExecutionPlan.reuse_traces``), a program is traced once, exported with
:mod:`jax.export` and kept under ``<compilation cache>/traced/``; a later process with the same key reads it back
and compiles it (a persistent-cache hit) without tracing. The file is JAX's serialised StableHLO, not a pickle:
reading it runs no Python. A file that cannot be read back (truncated, another format, not a regular file, too
big) is ignored and the program traced as before; the run never depends on the file. The programs kept: a
tabular run's init, training chunk and greedy evaluation, a sweep group's init, chunk and finish, and a PPO or SAC
run's evaluation and Brax's training epoch (:mod:`jaxrobo.deep.training`).

The key names everything a trace reads: the code of the ``jaxrobo``, ``envs`` and ``agents`` packages (their Python
and MJCF files, as a checkpoint's fingerprint hashes them); the functions patched into them (or into MJX) at run
time from a script, a test or a notebook (:func:`_live_code`: a patched step is another key, and undoing the patch
gives the first key back); the user's own modules the program's objects come from (a task or robot written outside
the packages: their files, or a notebook's functions, :func:`_user_code`); the versions of JAX, jaxlib, MuJoCo, MJX,
Brax and Flax; the backend and device kind; JAX's configuration; the execution plan; the objects the program is
built from (env, training config, learner, discretiser, evaluation sizes: :func:`describe` walks them, hashing
arrays by their bytes and functions by their code and what they close over); and the arguments' structure, shapes
and dtypes. What it does not follow is a patch inside JAX, jaxlib or another installed library, or one of the
packages' functions swapped for another of theirs: a process doing that sets ``JAXROBO_REUSE_TRACES=off`` (or
``JAXROBO_CACHE_DIR=off``, or runs a plan with ``reuse_traces=False``). Cold and warm runs execute the same
exported program, so a result does not depend on whether the trace was read back (``tests/test_reuse.py``).

Public surface: :func:`available`, :func:`compile_reusing` (and its first half, :func:`lower_reusing`),
:func:`kept_shapes`, :func:`describe`, :data:`LAST`, :data:`VARIABLE`.
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import os
import stat
import sys
import tempfile
import types
from typing import Any, Callable, Sequence

import jax
import numpy as np

#: The environment's switch: ``off`` (or 0, false, no) turns reuse off in every plan :meth:`for_run` makes.
VARIABLE = "JAXROBO_REUSE_TRACES"
#: A kept program bigger than this is not read (a training chunk exports to a few MB).
MAX_BYTES = 512 << 20
#: Custom calls our programs make that jax.export does not list as stable across JAX versions; the key holds the
#: JAX version, so a program is only ever read back by the version that wrote it.
_CUSTOM_CALLS = ("__gpu$xla.gpu.triton",)
#: The tree's packages: their own functions are not patches (:func:`_live_code`), nor their modules the user's.
#: (jaxrobo_ros, the robot-side node that jaxrobo.ros imports, runs in no traced program.)
_PACKAGES = ("jaxrobo", "envs", "agents", "jaxrobo_ros")


#: Attributes that cache programs made from an object's other fields (the evaluation's compiled flights, a
#: trainer's jitted init, an MJX simulator's jitted step): not inputs of a trace, and set or not depending on what
#: ran before the key.
_DERIVED = ("_compiled", "_jitted_init", "_jitted_steps", "_jitted_resets")


class NotKeyable(Exception):
    """An object the key cannot describe for certain (its repr names a memory address, or it is too large)."""


def available() -> bool:
    """Whether this process may reuse traces: ``JAXROBO_REUSE_TRACES`` not ``off`` and a persistent compilation
    cache in use."""
    from jaxrobo.core.environ import switch

    return switch(VARIABLE) and bool(jax.config.jax_compilation_cache_dir)


def _directory() -> str | None:
    base = jax.config.jax_compilation_cache_dir
    return os.path.join(str(base), "traced") if base else None


@functools.lru_cache(maxsize=1)
def _sources() -> str:
    """The packages' code as a checkpoint's fingerprint hashes it (:func:`jaxrobo.core.version.source_hash`), once a
    process (presets need not be in it: the config values they give are :func:`describe`'s)."""
    from jaxrobo.core.version import source_hash

    return source_hash()


def _code(code: types.CodeType, h: Any) -> None:
    """A code object's instructions, names and constants into ``h``, the same in every process (a set constant's
    order, which string hashing varies between processes, is sorted)."""
    h.update(code.co_code)
    h.update(repr((code.co_names, code.co_varnames, code.co_freevars)).encode())
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            _code(c, h)
        else:
            h.update(_constant(c).encode())


def _constant(c: Any) -> str:
    if isinstance(c, (frozenset, set)):
        return "{" + ",".join(sorted(_constant(i) for i in c)) + "}"
    if isinstance(c, tuple):
        return "(" + ",".join(_constant(i) for i in c) + ")"
    return repr(c)


def _roots() -> tuple[str, ...]:
    """The folders whose files :func:`_sources` hashes, and MJX's."""
    roots = [os.path.realpath(r) for name in _PACKAGES for r in getattr(sys.modules.get(name), "__path__", [])]
    mjx = sys.modules.get("mujoco.mjx")
    roots += [os.path.realpath(r) for r in getattr(mjx, "__path__", [])]
    return tuple(r + os.sep for r in roots)


def _foreign(f: types.FunctionType, home: tuple[str, ...], qualname: str,
             real: Callable[[str], str] = os.path.realpath) -> bool:
    """Whether ``f``, found where a function named ``qualname`` is defined, was written elsewhere by the user: in a
    script, a test, a notebook cell, ``python -c`` or the interpreter's prompt. A function that ``exec`` generated
    for its class (``<string>``: a dataclass's ``__init__``, named as where it sits) and a library's (a
    decorator's wrapper, ``dataclasses``' ``__repr__``) count as ``home``'s: they sit there by definition."""
    file = f.__code__.co_filename
    if file.startswith("<"):
        return not (file == "<string>" and f.__qualname__ == qualname)
    file = real(file)
    return not (file.startswith(home) or file.startswith(_library_places()))


def _functions(module: types.ModuleType) -> Any:
    """``(where, qualname, function)`` for each module-level function and each function of each class the module
    holds: where it sits, and the qualified name a function defined there has."""
    name = module.__name__
    for attr, value in sorted(getattr(module, "__dict__", {}).items()):
        if isinstance(value, types.FunctionType):
            yield f"{name}.{attr}", attr, value
        elif isinstance(value, type) and value.__module__ == name:
            for k, v in sorted(vars(value).items()):
                f = v.__func__ if isinstance(v, (staticmethod, classmethod)) else v
                if isinstance(f, types.FunctionType):
                    yield f"{name}.{attr}.{k}", f"{value.__qualname__}.{k}", f


def _live_code() -> str:
    """One hash of the functions patched into ``jaxrobo``, ``envs``, ``agents`` and MJX at run time: each
    module-level function and class function of their loaded modules whose code comes from a file outside them
    (a test's or a notebook's replacement), by where it sits and its code. Unpatched, it is the same whichever of
    their modules are loaded (their files are :func:`_sources`'s); a patch changes it, and undoing it changes it
    back. A swap of two of their own functions is not seen."""
    h = hashlib.sha256()
    home = _roots()
    # Resolved once per file, not per function: about 1,500 functions sit in about 150 files, and each realpath
    # costs system calls in every command's start-up (cpu-2cores/startup_seed_key.json).
    real = functools.lru_cache(maxsize=None)(os.path.realpath)
    for name in sorted(sys.modules):
        if name.split(".")[0] not in _PACKAGES and not name.startswith("mujoco.mjx"):
            continue
        for where, qualname, f in _functions(sys.modules[name]):
            if _foreign(f, home, qualname, real):
                h.update(where.encode())
                _code(f.__code__, h)
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _library_places() -> tuple[str, ...]:
    import site
    import sysconfig

    places = {sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    places.update(site.getsitepackages() if hasattr(site, "getsitepackages") else [])
    return tuple(os.path.realpath(p) + os.sep for p in places if p)


def _third_party(path: str) -> bool:
    """Whether ``path`` is the standard library's or an installed package's."""
    return os.path.realpath(path).startswith(_library_places())


def _user_code(modules: set[str]) -> str:
    """The code of the user's own modules that the described objects come from (a task or robot written outside
    the packages, docs/extending.md): each one's file, or for a module without one (a notebook's ``__main__``)
    every function it holds, with the functions patched into it from elsewhere."""
    h = hashlib.sha256()
    for name in sorted(modules):
        module = sys.modules.get(name)
        if module is None or name.split(".")[0] in _PACKAGES or name.split(".")[0] in ("builtins", "jax", "jaxlib",
                                                                                      "numpy", "mujoco"):
            continue
        path = getattr(module, "__file__", None)
        if path and _third_party(path):
            continue
        h.update(name.encode() + b"\0")
        if path and os.path.isfile(path):
            with open(path, "rb") as fh:
                h.update(hashlib.sha256(fh.read()).digest())
            own = os.path.realpath(path)
            for where, qualname, f in _functions(module):  # what was patched into it from elsewhere
                if os.path.realpath(f.__code__.co_filename) != own and _foreign(f, (), qualname):
                    h.update(where.encode())
                    _code(f.__code__, h)
        else:
            for where, _, f in _functions(module):
                h.update(where.encode())
                _code(f.__code__, h)
    return h.hexdigest()


def _versions() -> str:
    from jaxrobo.core.version import installed

    names = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "jax-cuda12-plugin", "brax", "flax")
    return repr([(d, installed(d)) for d in names])


def _device() -> str:
    d = jax.devices()[0]
    return f"{d.platform}:{getattr(d, 'device_kind', '')}:{jax.device_count()}:{jax.process_count()}"


def _jax_config() -> str:
    skip = ("cache", "log_compiles", "explain", "debug_log", "logging")
    values = getattr(jax.config, "values", {})
    return repr(sorted((k, repr(v)) for k, v in values.items() if not any(s in k for s in skip)))


def describe(obj: Any, *, limit: int = 50_000, modules: set[str] | None = None) -> str:
    """A text that determines ``obj`` as a trace sees it: plain values by repr, arrays by dtype, shape and a hash
    of their bytes, functions by qualified name, code and what they close over, a MuJoCo model by its saved
    bytes, containers, dataclasses and objects field by field.
    Raises :class:`NotKeyable` for what it cannot pin down (a repr with a memory address), or past ``limit``
    parts. ``modules`` (a set) receives the module of every class and function met (:func:`_user_code`)."""
    out: list[str] = []
    seen: dict[int, int] = {}
    if modules is None:
        modules = set()

    def walk(x: Any, depth: int) -> None:
        if len(out) > limit or depth > 40:
            raise NotKeyable("too large to describe")
        if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
            out.append(f"{type(x).__name__}:{x!r}")
            return
        if isinstance(x, np.generic):
            out.append(f"np:{x.dtype}:{x!r}")
            return
        if isinstance(x, (np.ndarray, jax.Array)):
            a = np.asarray(x)
            digest = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:32]
            out.append(f"array:{a.dtype}:{a.shape}:{digest}")
            return
        if isinstance(x, types.FunctionType):  # by name and code (every lambda is '<lambda>')
            modules.add(x.__module__)
            h = hashlib.sha256()
            _code(x.__code__, h)
            out.append(f"function:{x.__module__}.{x.__qualname__}:{h.hexdigest()[:32]}")
            if x.__closure__:  # what it closes over is part of what it does
                walk(tuple(c.cell_contents for c in x.__closure__ if _filled(c)), depth + 1)
            return
        if isinstance(x, type):
            modules.update(c.__module__ for c in x.__mro__)
        if isinstance(x, (type, types.BuiltinFunctionType, types.ModuleType)):
            out.append(f"{type(x).__name__}:{getattr(x, '__module__', '')}.{getattr(x, '__qualname__', x.__name__)}")
            return
        if isinstance(x, (jax.ShapeDtypeStruct,)):
            out.append(f"aval:{x.dtype}:{x.shape}")
            return
        if id(x) in seen:
            out.append(f"ref:{seen[id(x)]}")
            return
        seen[id(x)] = len(out)
        if isinstance(x, types.MethodType):
            out.append(f"method:{x.__func__.__qualname__}")
            walk(x.__self__, depth + 1)
            return
        if isinstance(x, functools.partial):
            out.append("partial")
            walk(x.func, depth + 1)
            walk(x.args, depth + 1)
            walk(sorted(x.keywords.items()), depth + 1)
            return
        wrapped = getattr(x, "__wrapped__", None)
        if wrapped is not None and callable(x):  # jax.jit's wrapper, functools.wraps
            out.append(f"wraps:{type(x).__name__}")
            walk(wrapped, depth + 1)
            return
        if isinstance(x, (list, tuple)):
            out.append(f"{type(x).__name__}:{len(x)}")
            for item in x:
                walk(item, depth + 1)
            return
        if isinstance(x, dict):
            out.append(f"dict:{len(x)}")
            for k in sorted(x, key=repr):
                walk(k, depth + 1)
                walk(x[k], depth + 1)
            return
        if isinstance(x, (set, frozenset)):
            out.append(f"{type(x).__name__}:{sorted(repr(i) for i in x)}")
            return
        kind = f"{type(x).__module__}.{type(x).__qualname__}"
        modules.update(c.__module__ for c in type(x).__mro__)
        if kind == "mujoco._structs.MjModel":  # a compiled MuJoCo model: all of it, as MuJoCo saves it
            import mujoco

            buf = np.zeros(mujoco.mj_sizeModel(x), np.uint8)
            mujoco.mj_saveModel(x, None, buf)
            out.append(f"{kind}:{hashlib.sha256(buf.tobytes()).hexdigest()[:32]}")
            return
        if dataclasses.is_dataclass(x):
            out.append(f"dataclass:{kind}")
            for f in dataclasses.fields(x):
                if f.metadata.get("host_only"):  # no program reads it (a seed): one trace serves every value
                    continue
                out.append(f.name)
                walk(getattr(x, f.name), depth + 1)
            return
        state = getattr(x, "__dict__", None)
        if state is not None:
            out.append(f"object:{kind}")
            for k in sorted(state):
                if k.startswith("_lock") or k in _DERIVED:  # a lock, or programs made from the other fields
                    continue
                out.append(k)
                walk(state[k], depth + 1)
            return
        text = repr(x)
        if " at 0x" in text:
            raise NotKeyable(f"{kind} has no description but its address")
        out.append(f"{kind}:{text}")

    walk(obj, 0)
    return "\n".join(out)


def _filled(cell: Any) -> bool:
    try:
        cell.cell_contents
    except ValueError:  # a cell not yet filled
        return False
    return True


def _key(name: str, parts: Any, plan: Any, args: Sequence[Any], donate: Sequence[int]) -> str:
    avals = jax.tree.map(lambda x: (tuple(np.shape(x)), str(getattr(x, "dtype", type(x).__name__))), args)
    modules: set[str] = set()
    described = describe(parts, modules=modules)
    text = "\n".join([name, _sources(), _live_code(), _user_code(modules), _versions(), _device(), _jax_config(),
                      _plan_text(plan), repr(sorted(donate)), str(jax.tree.structure(args)),
                      repr(jax.tree.leaves(avals)), described])
    return hashlib.sha256(text.encode()).hexdigest()


def _plan_text(plan: Any) -> str:
    return repr(sorted(plan.to_dict().items())) if hasattr(plan, "to_dict") else repr(plan)


def _is_namedtuple(x: Any) -> bool:
    return isinstance(x, tuple) and hasattr(type(x), "_fields")


def _structures_in(tree: Any, found: set[type]) -> set[type]:
    """The classes of the dataclass and named-tuple nodes of ``tree`` (another library's pytree nodes in a
    program's arguments: Brax's trainer state holds flax struct dataclasses and optax's named tuples)."""
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        found.add(type(tree))
        children: Any = [getattr(tree, f.name) for f in dataclasses.fields(tree)]
    elif isinstance(tree, (list, tuple)):
        if _is_namedtuple(tree):
            found.add(type(tree))
        children = tree
    elif isinstance(tree, dict):
        children = list(tree.values())
    else:
        return found
    for child in children:
        _structures_in(child, found)
    return found


def _register_structs(args: Any = ()) -> None:
    """jax.export serialises a pytree's structure: name jaxrobo's pytree dataclasses, and the dataclasses and
    named tuples met in ``args`` (static fields as Python literals), so it can."""
    from jax import export

    from jaxrobo.core import struct

    met = sorted(_structures_in(args, set()) - set(struct.DATACLASSES), key=lambda c: (c.__module__, c.__qualname__))
    for cls in list(struct.DATACLASSES) + met:
        if cls in _REGISTERED:
            continue
        name = f"{cls.__module__}.{cls.__qualname__}"
        try:
            if issubclass(cls, tuple):
                export.register_namedtuple_serialization(cls, serialized_name=name)
            else:
                export.register_pytree_node_serialization(
                    cls, serialized_name=name, serialize_auxdata=_aux_bytes, deserialize_auxdata=_aux_value)
        except ValueError:  # registered already (a module loaded twice under another name)
            pass
        _REGISTERED.add(cls)


_REGISTERED: set[type] = set()


#: How an enum member among a structure's static fields is written (a dict no literal aux holds by chance).
_ENUM = "__enum__"


#: What a ``convert`` of :func:`_rebuilt` returns for a value it leaves as it is.
_KEEP = object()


def _rebuilt(x: Any, convert: Callable[[Any], Any]) -> Any:
    """``x`` with every value ``convert`` replaces (it returns ``_KEEP`` for one it leaves) replaced, through plain
    lists, tuples and dicts; anything else is left as it is (and then must read back as a literal)."""
    got = convert(x)
    if got is not _KEEP:
        return got
    if type(x) in (list, tuple):
        return type(x)(_rebuilt(i, convert) for i in x)
    if type(x) is dict:
        return {k: _rebuilt(v, convert) for k, v in x.items()}
    return x


def _enum_to_literal(x: Any) -> Any:
    import enum

    if isinstance(x, enum.Enum):  # Brax's normaliser state names its mode with one
        return {_ENUM: (type(x).__module__, type(x).__qualname__, x.name)}
    return _KEEP


def _literal_to_enum(x: Any) -> Any:
    import enum

    if not (type(x) is dict and set(x) == {_ENUM}):
        return _KEEP
    module, qualname, name = x[_ENUM]
    cls: Any = sys.modules.get(module)  # only a module already loaded: reading a file imports nothing
    for part in str(qualname).split("."):
        cls = getattr(cls, part, None)
    if not (isinstance(cls, type) and issubclass(cls, enum.Enum)) or name not in cls.__members__:
        raise ValueError(f"kept structure names {module}.{qualname}.{name}, not a member of a loaded enum")
    return cls[name]


def _aux_bytes(aux: Any) -> bytes:
    text = repr(_rebuilt(aux, _enum_to_literal))
    try:
        same = _aux_value(text.encode()) == aux
    except (ValueError, SyntaxError, TypeError):
        same = False
    if not same:
        raise NotKeyable(f"static fields {text[:80]} do not read back as Python literals")
    return text.encode()


def _aux_value(data: bytes) -> Any:
    return _rebuilt(ast.literal_eval(data.decode()), _literal_to_enum)  # literals only: reading runs no code


def _read(path: str) -> Any | None:
    """The exported program kept at ``path``, or None (absent, not a regular file, too big, unreadable)."""
    from jax import export

    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_BYTES or st.st_size == 0:
            return None
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            data = fh.read(MAX_BYTES + 1)
    finally:
        if fd >= 0:
            os.close(fd)
    try:
        return export.deserialize(bytearray(data))
    except Exception:  # noqa: BLE001 - a damaged or foreign file: trace as if it were absent
        return None


def _write(path: str, data: bytes) -> None:
    """Atomically, beside the final name: a crash leaves no torn file under it, and a link there is replaced, not
    written through. A cache that cannot be written is not an error (the next run traces again). (The run
    directory's ``rundir.atomic_path`` sits in ``io``, a layer this module may not import; a cache file needs
    neither its ``fsync`` nor its permissions.)"""
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp.", dir=os.path.dirname(path))
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError:
        pass


#: What the last :func:`compile_reusing` of each name did: "read" (no trace), "traced" (kept for later runs) or
#: "off" (not reused: why follows). Tests and benchmarks read it.
LAST: dict[str, str] = {}


_READ: dict[str, Any] = {}  # kept programs this process has read, by path (kept_shapes, then compile_reusing)


def _kept(path: str, args: Sequence[Any]) -> Any | None:
    """The program kept at ``path`` if its arguments' structure and avals are ``args``'s (read once a process)."""
    exported = _READ.get(path) or _read(path)
    if exported is None:
        return None
    # (exported.call checks the avals too, when it is compiled for these arguments)
    if str(exported.in_tree) != str(jax.tree.structure((tuple(args), {}))) \
            or len(exported.in_avals) != len(jax.tree.leaves(args)):
        return None
    _READ[path] = exported
    return exported


def _path(plan: Any, name: str, args: Sequence[Any], parts: Any, donate: Sequence[int]) -> tuple[str | None, str]:
    """Where the program of this key is kept, or None and why not: the plan or the process does not reuse
    traces ("off"), or the key cannot describe ``parts`` ("off: ...")."""
    directory = _directory()
    if not (getattr(plan, "reuse_traces", False) and available() and directory):
        return None, "off"
    try:
        key = _key(name, parts, plan, args, donate)
    except NotKeyable as why:
        return None, f"off: {why}"
    _register_structs(args)
    return os.path.join(directory, f"{name}-{key[:40]}.jaxexport"), ""


def kept_shapes(plan: Any, name: str, args: Sequence[Any], parts: Any, *, donate: Sequence[int] = ()) -> Any | None:
    """The output's structure as ``jax.ShapeDtypeStruct`` leaves, read from the kept program of this key without
    tracing; None where there is none (then ``jax.eval_shape`` traces it, as before)."""
    path, _ = _path(plan, name, args, parts, donate)
    exported = None if path is None else _kept(path, args)
    if exported is None:
        return None
    return jax.tree.unflatten(exported.out_tree, [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.out_avals])


def compile_reusing(plan: Any, name: str, fn: Callable, args: Sequence[Any], parts: Any, *,
                    donate: Sequence[int] = ()) -> Callable:
    """``fn`` compiled for ``args`` under ``plan`` (traced under its trace-time choices, its compiler options),
    donating the arguments ``donate``; where ``plan.reuse_traces`` and :func:`available`, through a kept export
    named by :func:`_key` of ``name``, ``parts`` (what ``fn`` is built from) and the arguments."""
    return lower_reusing(plan, name, fn, args, parts, donate=donate).compile()


def lower_reusing(plan: Any, name: str, fn: Callable, args: Sequence[Any], parts: Any, *,
                  donate: Sequence[int] = ()) -> Any:
    """:func:`compile_reusing` up to XLA: the lowered program (``jax.stages.Lowered``), whose ``compile()`` a
    thread may run (XLA's compile holds no Python lock) while the caller traces the next program."""
    options = plan.xla_options
    kw: dict[str, Any] = {"donate_argnums": tuple(donate), "compiler_options": options}
    path, why = _path(plan, name, args, parts, donate)
    if path is None:
        LAST[name] = why
        with plan.tracing():
            return jax.jit(fn, **kw).lower(*args)
    from jax import export

    exported = _kept(path, args)
    if exported is not None:
        try:  # exported.call checks the arguments' structure and avals against the kept ones
            lowered = jax.jit(exported.call, **kw).lower(*args)
            LAST[name] = "read"
            return lowered
        except Exception:  # noqa: BLE001 - a kept program that does not fit these arguments: trace afresh
            pass
    with plan.tracing():
        exported = export.export(jax.jit(fn), disabled_checks=[
            export.DisabledSafetyCheck.custom_call(c) for c in _CUSTOM_CALLS])(*args)
    try:
        _write(path, exported.serialize())
        LAST[name] = "traced"
    except (NotKeyable, ValueError) as why:  # a structure jax.export cannot name: run it, keep nothing
        LAST[name] = f"off: {why}"
    return jax.jit(exported.call, **kw).lower(*args)
