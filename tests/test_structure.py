"""The import structure of ``jaxrobo/``, ``envs/`` and ``agents/``: no circles, and only the allowed directions.

Every ``import`` and ``from ... import`` is read with :mod:`ast`, module-level and inside functions alike (a
function-level import is still a dependency; it only runs later). An edge goes to the module the statement names:
``from jaxrobo.core import rng`` is an edge to ``jaxrobo.core.rng``, ``from jaxrobo import make`` one to
``jaxrobo`` (the package's ``__init__``). The parent packages Python initialises on the way are not edges: they
are never the cause of a circle unless a parent imports its child back, which is an edge of its own.

The layers:

* ``jaxrobo/`` is a stack of subpackages, :data:`LAYERS`, from the foundation up: a module imports modules of its
  own subpackage or of one listed below it, never one above (no upward imports between the subpackages). The
  commands (``jaxrobo.cli``, ``jaxrobo.check``), the package root and the public surface ``jaxrobo.api`` stand on
  top.
* ``envs/`` (robots and tasks) and ``agents/`` (tabular learners) import from jaxrobo only its public surface,
  :data:`PUBLIC_SURFACE` (``jaxrobo.api``; ``tests/test_public_api.py`` holds its names); a native-MuJoCo port
  (``envs/*/native.py``), which runs without JAX, its JAX-free base instead (:data:`NATIVE_SURFACE`). ``envs`` and
  ``agents`` never import each other.
* ``jaxrobo/`` reaches ``envs`` and the learners only through the registry's entry points
  (:data:`ENTRY_POINTS`: ``jaxrobo.task.registry`` imports them by name with importlib), and the exported runner
  the JAX-free task modules it is assembled from (:data:`RUNNER_SOURCES`).

No shims and no hidden switches, in ``jaxrobo/``, ``envs/`` and ``agents/``:

* no module writes into ``sys.modules`` or its own ``globals()`` (no aliases that make a module path importable
  under a second name; ``tests/test_public_api.py`` checks the old flat names do not import);
* no module-global knob read at trace time: a module of ``jaxrobo/``, ``envs/`` or ``agents/`` that imports JAX
  (its kernels and steps are traced) may not read, inside a function, an upper-case module global bound to a
  scalar constant (a number, string, bool or None: a setting, not a registry or a once-only warning set) that is
  a switch (bound to ``True``/``False``), rebound with ``global``, or overwritten from outside
  (``setattr(module, "NAME", ...)``, ``monkeypatch.setattr`` or ``module.NAME = ...`` anywhere in the repository);
  nor may any file set a package module's attributes by a computed name (``setattr(module, name, value)``), which
  hides which global it overwrites. A constant that only names a fact (a block size, a coefficient, a limit no
  one rebinds) is fine. A choice that changes what is traced belongs on
  :class:`jaxrobo.speed.plan.ExecutionPlan`, passed explicitly, where a cached program cannot miss it.
  :data:`KNOBS_ALLOWED_FOR_NOW` names any still waiting, each with what removes it.

Run ``python tests/test_structure.py`` to print the graph (the edges between subpackages and packages, and
circles).
"""
from __future__ import annotations

import ast
import os
import re
import sys
from typing import NamedTuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = ("jaxrobo", "envs", "agents")

#: The subpackages of ``jaxrobo/``, from the foundation up; a module may import its own subpackage's modules and
#: those of the layers below. Siblings in one tuple are independent (neither imports the other).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("core",),                 # pytree dataclasses, keys, spaces, validated YAML, precision, version
    ("physics", "tabular"),    # simulators and their trace-time switches; the learner protocol, the discretiser
    ("task",),                 # TaskEnv and its hooks, Robot, registry, autoreset, wrappers, rollouts
    ("speed", "io"),           # the execution plan and kernels, compile cache, sharding; run directories and files
    ("training",),             # trainer, driver, train(), run resolution, budget, checkpoints, summaries, sweeps
    ("pictures",),             # frames and videos, reward plots, flights
    ("interop",),              # Gymnasium and Brax faces
    ("deep",),                 # Brax's PPO/SAC trainers on the Brax face
)
#: The modules on top of every layer: the package root, its public surface and the commands (``check``, ``show``,
#: ``export``, ``evaluate``).
TOP = frozenset({"jaxrobo", "jaxrobo.api", "jaxrobo.cli", "jaxrobo.check", "jaxrobo.show", "jaxrobo.export",
                 "jaxrobo.evaluate"})
#: The one module ``envs/`` and ``agents/`` import from jaxrobo.
PUBLIC_SURFACE = frozenset({"jaxrobo.api"})
#: What a native-MuJoCo port (``envs/*/native.py``) imports from jaxrobo instead: its JAX-free base and the
#: exported runner's robot side (the public surface imports JAX, and a port runs an export without it).
NATIVE_SURFACE = frozenset({"jaxrobo.interop.native", "jaxrobo.interop.numpy_policy"})
#: The jaxrobo modules that may import envs/agents (by entry-point name, with importlib, in practice).
ENTRY_POINTS = frozenset({"jaxrobo.task.registry"})
#: The exported runner's robot side computes with the tasks' own JAX-free step functions, which ``jaxrobo export``
#: writes into the runner's file (:func:`jaxrobo.export.runner_source`): the one jaxrobo module that imports them.
RUNNER, RUNNER_SOURCES = "jaxrobo.interop.numpy_policy", frozenset({"envs.quadcopter.geometry",
                                                                    "envs.quadcopter.goto_step", "envs.cartpole.rules"})

#: Edges that break the rules and are waiting to be removed, each with what removes it. Empty: nothing is excused,
#: and a new forbidden edge fails the test.
ALLOWED_FOR_NOW: dict[tuple[str, str], str] = {}

#: The modules that write into ``sys.modules``, and why. ``jaxrobo.physics.mjx_import``: while ``mujoco.mjx``
#: imports, stand-ins for its mesh libraries (trimesh, scipy.spatial; seconds of every MJX command's start-up),
#: removed right after. ``jaxrobo.interop.deferred_imports``: stand-ins for JAXopt and Orbax, which Brax imports and
#: a jaxrobo run never calls (0.83 s of import in every PPO/SAC command on 2 cores, ``python -X importtime``).
#: ``jaxrobo.core.deferred``: the stand-in both use, which puts the real module in its place on first use. Tricks
#: on libraries' imports, version-guarded and tested (``tests/test_mjx_import.py``,
#: ``tests/test_deferred_imports.py``); no alias of a jaxrobo module. Any other write fails the test.
SYS_MODULES_WRITERS = frozenset({"jaxrobo.physics.mjx_import", "jaxrobo.interop.deferred_imports",
                                 "jaxrobo.core.deferred"})

#: Module-global knobs still read at trace time, ``(module, name)``, each with what removes it. A knob that is
#: gone must come off (``test_knobs_allowed_for_now_still_exist``); a new one fails the test.
KNOBS_ALLOWED_FOR_NOW: dict[tuple[str, str], str] = {}

#: Folders whose Python may overwrite a jaxrobo module's globals (where an outside write is looked for).
WRITERS = ("jaxrobo", "envs", "agents", "tests", "benchmarks", "scripts", "examples")

#: The project's style: no line of its Python is longer than this, in the folders that hold it (every ``.py`` file
#: the repository tracks lies in one of them) and in any ``.py`` file at the repository's root.
MAX_LINE = 120
LINE_FOLDERS = WRITERS + ("jaxrobo_ros",)


class Edge(NamedTuple):
    src: str
    dst: str
    path: str
    line: int
    in_function: bool

    def __str__(self) -> str:
        where = "function-level" if self.in_function else "module-level"
        return f"{self.src} -> {self.dst}  ({self.path}:{self.line}, {where})"


def modules() -> dict[str, str]:
    """``{dotted module name: file path}`` of every module of the three packages."""
    found = {}
    for pkg in PACKAGES:
        for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, pkg)):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            rel = os.path.relpath(dirpath, ROOT).split(os.sep)
            for name in filenames:
                if name.endswith(".py"):
                    parts = rel if name == "__init__.py" else rel + [name[:-3]]
                    found[".".join(parts)] = os.path.join(dirpath, name)
    return found


def _resolve(name: str, known: dict[str, str]) -> str | None:
    """The longest known module ``name`` starts with (``jaxrobo.physics.sim.mjx`` -> ``jaxrobo.physics.sim``); None if
    outside."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in known:
            return candidate
        parts.pop()
    return None


def import_edges() -> list[Edge]:
    known = modules()
    edges = []
    for module, path in sorted(known.items()):
        tree = ast.parse(open(path, encoding="utf-8").read(), path)
        is_package = os.path.basename(path) == "__init__.py"
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))]
        in_function = {id(inner) for f in functions for inner in ast.walk(f) if inner is not f}
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: resolve against this module's package
                    package = module.split(".") if is_package else module.split(".")[:-1]
                    package = package[: len(package) - (node.level - 1)]
                    base = ".".join(package + ([base] if base else []))
                # `from pkg import sub` names the submodule when there is one, else the package itself
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
            for target in targets:
                dst = _resolve(target, known)
                if dst is not None and dst != module:
                    edges.append(Edge(module, dst, os.path.relpath(path, ROOT), node.lineno, id(node) in in_function))
    return sorted(set(edges), key=lambda e: (e.src, e.dst, e.line))


def circles(edges: list[Edge]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.src, set()).add(e.dst)
        graph.setdefault(e.dst, set())
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def _top(module: str) -> str:
    return module.split(".")[0]


def layer(module: str) -> int | None:
    """The index in :data:`LAYERS` of a ``jaxrobo`` module's subpackage; ``len(LAYERS)`` for :data:`TOP`; None for
    a module of no listed subpackage (a new one, which :func:`test_every_module_has_a_layer` reports)."""
    if module in TOP:
        return len(LAYERS)
    parts = module.split(".")
    if parts[0] != "jaxrobo" or len(parts) < 2:
        return None
    for i, group in enumerate(LAYERS):
        if parts[1] in group:
            return i
    return None


def _subpackage(module: str) -> str:
    return module.split(".")[1] if module not in TOP else module


def forbidden(edge: Edge) -> str | None:
    """Why ``edge`` breaks a layering rule, or None if it is allowed."""
    src, dst = _top(edge.src), _top(edge.dst)
    if src == dst == "jaxrobo":
        a, b = layer(edge.src), layer(edge.dst)
        if a == b == len(LAYERS):  # the top modules use each other freely
            return None
        if a is not None and b is not None and _subpackage(edge.src) != _subpackage(edge.dst) and b >= a:
            if b > a:
                return (f"upward: {_subpackage(edge.src)} (layer {a}) must not import "
                        f"{_subpackage(edge.dst)} (layer {b})")
            return f"sideways: {_subpackage(edge.src)} and {_subpackage(edge.dst)} are siblings of layer {a}"
        return None
    if src == "envs" and dst == "agents":
        return "envs must not import agents (tasks know nothing of learners)"
    if src == "agents" and dst == "envs":
        return "agents must not import envs (learners know nothing of tasks)"
    if src == "envs" and edge.src.endswith(".native") and edge.dst in NATIVE_SURFACE:
        return None
    if src in ("envs", "agents") and dst == "jaxrobo" and edge.dst not in PUBLIC_SURFACE:
        return f"{src} may import only the public surface ({', '.join(sorted(PUBLIC_SURFACE))}) from jaxrobo"
    if edge.src == RUNNER and edge.dst in RUNNER_SOURCES:
        return None
    if src == "jaxrobo" and dst in ("envs", "agents") and edge.src not in ENTRY_POINTS:
        return f"jaxrobo reaches {dst} only through the registry's entry points ({', '.join(sorted(ENTRY_POINTS))})"
    return None


def _cycle_edges(component: list[str], edges: list[Edge]) -> list[Edge]:
    members = set(component)
    return sorted({e for e in edges if e.src in members and e.dst in members}, key=lambda e: (e.src, e.dst, e.line))


# ---- shims and knobs -----------------------------------------------------------------------------------------
_KNOB_NAME = re.compile(r"^_?[A-Z][A-Z0-9_]*$")


def _aliases(tree: ast.AST) -> dict[str, str]:
    """``{local name: dotted module or object}`` from a file's imports (``import a.b as c``, ``from a import b``)."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                out[a.asname or a.name] = f"{node.module}.{a.name}"
    return out


def module_aliasing(sources: dict[str, str]) -> list[str]:
    """``module:line`` of each write into ``sys.modules`` or into a module's own ``globals()``."""
    found = []
    for module, text in sorted(sources.items()):
        tree = ast.parse(text)
        names = _aliases(tree)

        def is_sys_modules(node) -> bool:
            return (isinstance(node, ast.Attribute) and node.attr == "modules" and isinstance(node.value, ast.Name)
                    and names.get(node.value.id) == "sys")

        def is_globals(node) -> bool:
            return isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "globals"

        for node in ast.walk(tree):
            target = None
            if isinstance(node, (ast.Assign, ast.AugAssign, ast.Delete)):
                for t in getattr(node, "targets", None) or [node.target]:
                    if isinstance(t, ast.Subscript) and (is_sys_modules(t.value) or is_globals(t.value)):
                        target = t
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                  and node.func.attr in ("setdefault", "update", "__setitem__", "pop", "__delitem__")
                  and (is_sys_modules(node.func.value) or is_globals(node.func.value))):
                target = node
            if target is not None:
                found.append(f"{module}:{node.lineno}")
    return found


def _scalar(node: ast.AST) -> bool:
    """Whether ``node`` is a constant scalar expression (``32``, ``-1.5``, ``256 << 20``, ``True``, ``"a"``)."""
    if isinstance(node, ast.Constant):
        return node.value is None or isinstance(node.value, (bool, int, float, str))
    if isinstance(node, ast.UnaryOp):
        return _scalar(node.operand)
    if isinstance(node, ast.BinOp):
        return _scalar(node.left) and _scalar(node.right)
    return False


def module_knobs(sources: dict[str, str], writers: dict[str, str]) -> dict[tuple[str, str], str]:
    """``{(module, NAME): why}`` for each knob (see the module docstring) of the modules in ``sources``; ``writers``
    is every file that may overwrite one from outside, ``{path: source}``. A write by a computed name into a
    module of ``sources`` is reported as ``(module, "*")``."""
    written: set[tuple[str, str]] = set()
    found = {}
    for text in writers.values():
        tree = ast.parse(text)
        names = _aliases(tree)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and len(node.args) >= 2 and isinstance(node.args[0], ast.Name)
                    and ((isinstance(node.func, ast.Name) and node.func.id == "setattr")
                         or (isinstance(node.func, ast.Attribute) and node.func.attr == "setattr"))):
                target = names.get(node.args[0].id, node.args[0].id)
                if isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str):
                    written.add((target, node.args[1].value))
                elif target in sources:
                    found[(target, "*")] = "attributes set by a computed name from outside its module"
            if isinstance(node, ast.Assign):
                for t in node.targets:
                    if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name):
                        written.add((names.get(t.value.id, t.value.id), t.attr))
    for module, text in sorted(sources.items()):
        tree = ast.parse(text)
        if not any(v == "jax" or v.startswith("jax.") for v in _aliases(tree).values()):
            continue  # nothing of this module is traced
        bound: dict[str, ast.AST] = {}
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, ast.AnnAssign) and node.value is not None else []
            for t in targets:
                if isinstance(t, ast.Name) and _KNOB_NAME.match(t.id) and _scalar(node.value):
                    bound[t.id] = node.value
        rebound = {n for node in ast.walk(tree) if isinstance(node, ast.Global) for n in node.names}
        read_in_function = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                read_in_function |= {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)
                                     and isinstance(n.ctx, ast.Load)}
        for name, value in bound.items():
            if name not in read_in_function:
                continue
            if isinstance(value, ast.Constant) and isinstance(value.value, bool):
                found[(module, name)] = "a module-level switch"
            elif name in rebound:
                found[(module, name)] = "rebound with `global`"
            elif (module, name) in written:
                found[(module, name)] = "overwritten from outside its module"
    return found


def _sources(packages=("jaxrobo",)) -> dict[str, str]:
    out = {}
    for module, path in modules().items():
        if module.split(".")[0] in packages:
            with open(path, encoding="utf-8") as f:
                out[module] = f.read()
    return out


def _writer_sources() -> dict[str, str]:
    out = {}
    for folder in WRITERS:
        for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, folder)):
            dirnames[:] = [d for d in dirnames if d not in ("__pycache__", "results")]
            for name in filenames:
                if name.endswith(".py"):
                    path = os.path.join(dirpath, name)
                    with open(path, encoding="utf-8") as f:
                        out[path] = f.read()
    return out


def long_lines(limit: int = MAX_LINE) -> list[str]:
    """``path:line (N characters)`` of each line longer than ``limit`` characters in the Python of
    :data:`LINE_FOLDERS` and of the repository's root."""
    paths = sorted(os.path.join(ROOT, name) for name in os.listdir(ROOT) if name.endswith(".py"))
    for folder in LINE_FOLDERS:
        for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, folder)):
            dirnames[:] = sorted(d for d in dirnames if d not in ("__pycache__", "results"))
            paths += [os.path.join(dirpath, name) for name in sorted(filenames) if name.endswith(".py")]
    found = []
    for path in paths:
        with open(path, encoding="utf-8") as f:
            for number, line in enumerate(f, 1):
                length = len(line.rstrip("\r\n"))
                if length > limit:
                    found.append(f"{os.path.relpath(path, ROOT)}:{number} ({length} characters)")
    return found


# ---- tests ---------------------------------------------------------------------------------------------------
def test_every_package_is_parsed():
    known = modules()
    for pkg in PACKAGES:
        assert pkg in known, f"{pkg}/__init__.py not found under {ROOT}"
    assert {"jaxrobo.physics.sim", "jaxrobo.task.registry", "envs.cartpole.robot",
            "jaxrobo.tabular.learner"} <= set(known)
    assert any(e.src == "envs.cartpole.robot" and e.dst == "jaxrobo.api" for e in import_edges())


def test_no_import_circles():
    edges = [e for e in import_edges() if (e.src, e.dst) not in ALLOWED_FOR_NOW]
    found = circles(edges)
    message = "\n\n".join("circle: " + " <-> ".join(c) + "\n  " + "\n  ".join(map(str, _cycle_edges(c, edges)))
                          for c in found)
    assert not found, f"import circles between modules:\n{message}"


def test_no_forbidden_import_direction():
    bad = [(e, why) for e in import_edges() if (why := forbidden(e)) and (e.src, e.dst) not in ALLOWED_FOR_NOW]
    message = "\n".join(f"{e}\n    {why}" for e, why in bad)
    assert not bad, f"imports against the layering:\n{message}"


def test_allowed_for_now_lists_only_edges_that_still_exist():
    """An edge that is gone comes off the list, so the list cannot hide a new one of the same pair later."""
    present = {(e.src, e.dst) for e in import_edges()}
    stale = sorted(set(ALLOWED_FOR_NOW) - present)
    assert not stale, "edges in ALLOWED_FOR_NOW that no longer exist (remove them): " + ", ".join(
        f"{a} -> {b}" for a, b in stale)


def test_the_checker_finds_circles_and_forbidden_edges():
    """The graph code itself: a made-up circle and made-up upward edges are reported."""
    e = lambda a, b: Edge(a, b, "x.py", 1, False)  # noqa: E731
    assert circles([e("jaxrobo.a", "jaxrobo.b"), e("jaxrobo.b", "jaxrobo.c"), e("jaxrobo.c", "jaxrobo.a"),
                    e("jaxrobo.c", "jaxrobo.d")]) == [["jaxrobo.a", "jaxrobo.b", "jaxrobo.c"]]
    assert forbidden(e("jaxrobo.physics.sim", "envs")) and forbidden(e("jaxrobo.training.train", "agents.qlearning"))
    assert forbidden(e("envs.x", "jaxrobo.tabular.learner")) and forbidden(e("agents.sarsa", "envs.cartpole.robot"))
    assert forbidden(e("envs.x", "jaxrobo.training.train")) and forbidden(e("agents.sarsa", "jaxrobo.task.env"))
    assert not forbidden(e("jaxrobo.task.registry", "envs"))
    assert not forbidden(e("jaxrobo.training.train", "jaxrobo.tabular.learner"))
    assert (forbidden(e("envs.cartpole.robot", "jaxrobo.physics.sim"))
            and forbidden(e("agents.sarsa", "jaxrobo.core.rng")))
    assert not forbidden(e("envs.cartpole.robot", "jaxrobo.api")) and not forbidden(e("agents.sarsa", "jaxrobo.api"))
    assert forbidden(e("agents.sarsa", "jaxrobo.tabular.learner"))
    assert forbidden(e("jaxrobo.training.trainer", "agents.tabular"))
    # between subpackages: down is allowed, up and sideways are not; inside one subpackage anything goes
    assert forbidden(e("jaxrobo.physics.sim", "jaxrobo.task.env"))          # up
    assert forbidden(e("jaxrobo.physics.sim", "jaxrobo.tabular.learner"))   # sideways
    assert forbidden(e("jaxrobo.core.config", "jaxrobo.cli"))               # up to the top
    assert not forbidden(e("jaxrobo.cli", "jaxrobo.core.config"))
    assert not forbidden(e("jaxrobo.training.driver", "jaxrobo.training.trainer"))


def test_import_jaxrobo_loads_no_jax():
    """In a fresh process, ``import jaxrobo``, ``import envs`` and a native port (``envs.quadcopter.native``) load
    neither JAX nor MJX, yet every id is registered with Gymnasium and :class:`ConfigError` and the registry work;
    the package root's JAX names load on first access, ``dir`` lists them, and ``gymnasium.make`` builds the env
    (importing JAX then) with the task's step limit, which its spec reads when asked, also from a copy."""
    import subprocess

    code = ("import sys, gymnasium as gym\n"
            "import jaxrobo, envs, envs.quadcopter.native\n"
            "from jaxrobo.core.config import ConfigError\n"
            "from jaxrobo.api import register, scalar\n"
            "assert 'jaxrobo/CartPoleStayUp-v0' in gym.registry and 'CartPoleStayUp-v0' in jaxrobo.registered()\n"
            "print(sorted(m for m in ('jax', 'jaxlib', 'mujoco.mjx') if m in sys.modules))\n"
            "print(sorted(set(jaxrobo.__all__) - set(dir(jaxrobo))), jaxrobo.TaskEnv.__module__, "
            "'jax' in sys.modules)\n"
            "import copy\n"  # gymnasium.make_vec reads the step limit from a deep copy of the spec
            "print(copy.deepcopy(gym.spec('jaxrobo/CartPoleStayUp-v0')).max_episode_steps)\n"
            "env = gym.make('jaxrobo/CartPoleStayUp-v0')\n"
            "print(type(env.unwrapped).__name__, env.spec.max_episode_steps, "
            "jaxrobo.spec('CartPoleStayUp-v0').max_episode_steps)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT})
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.splitlines() == ["[]", "[] jaxrobo.task.env True", "1000", "JaxroboEnv 1000 1000"], out.stdout


def test_no_sys_modules_aliasing():
    """No module path is made importable under a second name, and no module plants names in its own globals."""
    found = [m for m in module_aliasing(_sources(PACKAGES)) if m.split(":")[0] not in SYS_MODULES_WRITERS]
    assert not found, "writes into sys.modules or globals() (aliases, shims): " + ", ".join(found)


def test_no_module_global_knobs_read_at_trace_time():
    found = module_knobs(_sources(PACKAGES), _writer_sources())
    new = {k: why for k, why in found.items() if k not in KNOBS_ALLOWED_FOR_NOW}
    assert not new, "module-global knobs read at trace time (make them ExecutionPlan fields):\n" + "\n".join(
        f"  {m}.{n}: {why}" for (m, n), why in sorted(new.items()))


def test_knobs_allowed_for_now_still_exist():
    """A knob that is gone comes off the list, so the list cannot excuse a new one of the same name later."""
    stale = sorted(set(KNOBS_ALLOWED_FOR_NOW) - set(module_knobs(_sources(PACKAGES), _writer_sources())))
    assert not stale, "KNOBS_ALLOWED_FOR_NOW lists knobs that no longer exist (remove them): " + ", ".join(
        f"{m}.{n}" for m, n in stale)


def test_the_checker_finds_aliases_and_knobs():
    """The checks themselves, on made-up modules: each kind of alias and knob is found, constants are not."""
    assert module_aliasing({"jaxrobo.x": "import sys as _s\n_s.modules.setdefault('jaxrobo.y', _s)\n",
                            "jaxrobo.z": "import sys\nsys.modules['a'] = sys\n",
                            "jaxrobo.g": "globals().setdefault('env', 1)\n",
                            "jaxrobo.ok": "import sys\nif 'm' in sys.modules: pass\n"}) == [
        "jaxrobo.g:1", "jaxrobo.x:2", "jaxrobo.z:2"]
    src = ("import jax\nFLAG = False\nLIMIT = 0.78\nSIZE = 32\nCOUNT = 0\nUNUSED = True\n_SEEN = set()\n"
           "def f(x):\n    global COUNT\n    COUNT += 1\n    _SEEN.add(x)\n"
           "    return (x * LIMIT if FLAG else x + SIZE) + COUNT\n")
    writer = ("import jaxrobo.k as k\ndef t(monkeypatch):\n    monkeypatch.setattr(k, 'LIMIT', 1.0)\n"
              "    monkeypatch.setattr(k, '_SEEN', set())\n")
    assert module_knobs({"jaxrobo.k": src}, {"t.py": writer}) == {
        ("jaxrobo.k", "FLAG"): "a module-level switch", ("jaxrobo.k", "LIMIT"): "overwritten from outside its module",
        ("jaxrobo.k", "COUNT"): "rebound with `global`"}
    assert module_knobs({"jaxrobo.k": src.replace("import jax", "import numpy")}, {"t.py": writer}) == {}
    # A task's kernel under envs/ is held to the same rule; a None default overwritten from outside is a knob, and
    # a write by a computed name (a benchmark setting several knobs in a loop) is reported on its own.
    kernel = "import jax\nWARPS: int | None = None\nBLOCK = 32\ndef k(x):\n    return x * (WARPS or BLOCK)\n"
    bench = ("from envs.cartpole import kernel\nkernel.WARPS = 2\n"
             "for name, v in {'BLOCK': 64}.items():\n    setattr(kernel, name, v)\n")
    assert module_knobs({"envs.cartpole.kernel": kernel}, {"b.py": bench}) == {
        ("envs.cartpole.kernel", "WARPS"): "overwritten from outside its module",
        ("envs.cartpole.kernel", "*"): "attributes set by a computed name from outside its module"}
    assert module_knobs({"envs.cartpole.kernel": kernel}, {}) == {}


def test_no_line_over_the_limit():
    """Every line of the repository's Python is at most :data:`MAX_LINE` characters (wrap a longer one: reflow the
    docstring or comment, split the expression inside parentheses)."""
    found = long_lines()
    assert not found, f"lines over {MAX_LINE} characters:\n" + "\n".join(f"  {where}" for where in found)


def report() -> str:
    """The graph as text: circles, then every edge between the three packages or breaking a rule."""
    edges = import_edges()
    found = circles(edges)
    lines = ["circles (edges allowed for now included):"] + (["  " + " <-> ".join(c) for c in found] or ["  none"])
    lines.append("edges across packages (src -> dst), [!] against the layering, [allowed for now] listed:")
    for e in sorted(set(edges), key=lambda e: (e.src, e.dst, e.line)):
        why = forbidden(e)
        allowed = (e.src, e.dst) in ALLOWED_FOR_NOW
        across = _top(e.src) != _top(e.dst) or (e.src.count(".") and e.dst.count(".")
                                                  and e.src.split(".")[1] != e.dst.split(".")[1])
        if across or why or allowed:
            tag = " [allowed for now]" if allowed else (" [!]" if why else "")
            lines.append(f"  {e}{tag}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(print(report()))
