"""``jaxrobo export RUN --out DIR``: a trained policy as a small self-describing file and a numpy-only runner.

``DIR`` receives ``policy.json`` (what the policy is: format, kind, env id, observation and action layout, the env's
options and parameters as the run set them, where it came from), ``policy.npz`` (its numbers, plain arrays) and
``jaxrobo_policy.py`` (:mod:`jaxrobo.interop.numpy_policy` with the task modules it computes with,
:func:`runner_source`; importing only numpy): ``Policy.load(DIR)(obs) -> action`` outside JAX. A deep run also gets
``policy.onnx`` where the ``onnx`` package is installed (``pip install jaxrobo[export]``). For a task with a native
port, ``policy.json`` also holds a ``robot`` section (:func:`jaxrobo.ros.bridge.robot_section`: the control period, the
observation's constants, the action table), from which the runner turns the robot's readings into observations and
actions into commands (``policy.io``): what the ROS policy node (:mod:`jaxrobo_ros`) works from, without JAX.

* A **tabular** run: the discretiser rebuilt from the run's ``config.yaml`` exactly as training built it
  (:func:`jaxrobo.training.trainer.make_discretiser_for`; checked against the one saved in ``qtables.npz``) and the
  greedy action of every state of one table (``--table``; default the run's selected best table, else 0): the first
  maximal action value (``ties="first"`` of :func:`jaxrobo.task.rollout.greedy_policy`; the evaluation in JAX
  breaks ties at random, ``n_max`` counts the maximal actions of each state so ties are visible), with the action
  values themselves (``values``, summed over Double Q-learning's two tables as the learner acts).
* A **PPO/SAC** run (:mod:`jaxrobo.deep.policy`): the observation normaliser's mean and std, each dense layer's
  kernel and bias, the activation and distribution of Brax's network maker (read from its signature, so a Brax
  that changed them is refused rather than exported wrong), and the affine map of Brax's ``[-1, 1]`` onto the
  task's action bounds (:meth:`jaxrobo.interop.brax_env.BraxEnv.scale_action`).

Refused, with a one-line error naming the path or field and nothing written: a path that is not a run directory, an
unfinished run, a sweep, a learner that is neither a registered tabular learner nor ppo/sac, a run whose files do
not match its config, an existing non-empty ``--out`` without ``--overwrite``.
"""
from __future__ import annotations

import argparse
import ast
import importlib.util
import inspect
import os
import sys
from typing import Any

import numpy as np

from jaxrobo_ros.policy_node import RUNNER as RUNNER_NAME  # the runner copied into every export: its name there


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN", help="a finished run directory of `jaxrobo train`")
    parser.add_argument("--out", required=True, help="directory to write policy.json, policy.npz, jaxrobo_policy.py")
    parser.add_argument("--table", type=int, default=None,
                        help="tabular runs: which trained table (env index); default the run's selected best "
                             "table (summary.json), else 0")
    parser.add_argument("--overwrite", action="store_true", help="replace what --out holds")
    parser.add_argument("--no-onnx", action="store_true", help="deep runs: do not write policy.onnx")


def run(args: argparse.Namespace) -> int:
    from jaxrobo.core.config import ConfigError

    try:
        meta = export_run(args.run_dir, args.out, table=args.table, overwrite=args.overwrite, onnx=not args.no_onnx)
    except ConfigError as err:
        print(f"jaxrobo export: {err}", file=sys.stderr)
        return 2
    what = (f"table {meta['table']} of {meta['learner']}: {meta['n_states']} states x {meta['n_actions']} actions "
            f"({meta['tied_states']} states with tied maxima: first maximum taken)" if meta["kind"] == "tabular"
            else f"{meta['agent']} MLP {meta['observation_size']} -> {meta['layer_sizes']} ({meta['activation']})")
    print(f"{meta['env_id']}: {what} -> {args.out}")
    for name in sorted(os.listdir(args.out)):
        print(f"  {os.path.join(args.out, name)}")
    return 0


# ---- reading the run ------------------------------------------------------------------------------------
def _check_run_dir(run_dir: str) -> dict[str, Any]:
    """The run's config, once the directory is a finished run of one training (ConfigError naming it)."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io import rundir
    from jaxrobo.io.results import load_config

    if not os.path.isdir(run_dir):
        raise ConfigError(f"{run_dir}: not a directory (expected a run directory of `jaxrobo train`)")
    if os.path.exists(os.path.join(run_dir, "sweep.csv")):
        raise ConfigError(f"{run_dir}: a sweep directory; export one run of it (`jaxrobo train` with that row's "
                          "values)")
    try:
        cfg = load_config(run_dir)
    except FileNotFoundError as err:
        raise ConfigError(str(err)) from None
    if not rundir.is_complete(run_dir):
        status = (rundir.read_status(run_dir) or {}).get("status", "no status.json")
        raise ConfigError(f"{run_dir}: the run is not complete (status: {status}); finish it first "
                          "(`jaxrobo train --resume` for an interrupted tabular run)")
    if not isinstance(cfg.get("env_id"), str) or not isinstance(cfg.get("train"), dict):
        raise ConfigError(f"{os.path.join(run_dir, 'config.yaml')}: env_id or train is missing; is it a jaxrobo "
                          "run directory?")
    return cfg


def _agent(cfg: dict[str, Any], where: str) -> str:
    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError
    from jaxrobo.task import registry

    agent = cfg["train"].get("agent")
    if not (deep.is_deep(agent) or agent in registry.learners()):
        raise ConfigError(f"{where}: train.agent={agent!r} is not a learner jaxrobo can export: "
                          f"{', '.join(registry.learners())} (tabular) or {', '.join(deep.AGENTS)}")
    return agent


def _pick_table(run_dir: str, q: np.ndarray, table: int | None) -> int:
    from jaxrobo.core.config import ConfigError

    from jaxrobo.io.results import selected_table

    if table is None:
        table = selected_table(run_dir, q.shape[0])
    elif not 0 <= table < q.shape[0]:
        raise ConfigError(f"--table {table}: must be in 0..{q.shape[0] - 1} (the run has {q.shape[0]} tables)")
    if not np.all(np.isfinite(q[table])):
        raise ConfigError(f"{os.path.join(run_dir, 'qtables.npz')}: table {table} holds non-finite values; it cannot "
                          "be exported")
    return table


# ---- tabular --------------------------------------------------------------------------------------------
def tabular_export(run_dir: str, cfg: dict[str, Any], table: int | None) -> tuple[dict, dict]:
    """``(meta, arrays)`` of a tabular run's greedy policy (see the module's docstring)."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import check_saved_discretiser, load_tables
    from jaxrobo.training.run import check_tables, spec_from_config
    from jaxrobo.training.trainer import make_discretiser_for

    where = os.path.join(run_dir, "config.yaml")
    try:
        spec = spec_from_config(cfg, check_memory=False)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
    disc = make_discretiser_for(spec.env, spec.config)
    saved = load_tables(run_dir)
    q = saved["q"]
    n_actions = int(spec.env.num_actions)
    tables_path = os.path.join(run_dir, "qtables.npz")
    check_tables(q, spec.env, spec.config, tables_path)
    check_saved_discretiser(saved, disc, tables_path)
    low, width = np.asarray(disc.low, np.float32), np.asarray(disc.width, np.float32)
    table = _pick_table(run_dir, q, table)
    rows = q[table].astype(np.float32)
    # The policy's values as the learner acts on them (jaxrobo.tabular.learner.policy_values): one table, or the
    # float32 sum of Double Q-learning's two (one addition per entry: the same number as in JAX).
    values = rows[0] if rows.shape[0] == 1 else np.add.reduce(rows, axis=0, dtype=np.float32)
    n_max = (values == values.max(axis=1, keepdims=True)).sum(axis=1).astype(np.int32)
    arrays: dict[str, np.ndarray] = {"action": np.argmax(values, axis=1).astype(np.int32), "n_max": n_max,
                                     "values": values, "bins": np.asarray(disc.bins, np.int64)}
    if disc.edges is not None:
        for i, e in enumerate(disc.edges):
            arrays[f"edges_{i}"] = np.asarray(e, np.float32)
    else:
        arrays.update(low=low, width=width)
    space = spec.env.observation_space()
    meta = {"format": 1, "kind": "tabular", "env_id": spec.env_id, "observation_size": int(space.shape[0]),
            "observation_names": list(getattr(space, "names", None) or []), "n_actions": n_actions,
            "discretiser": "edges" if disc.edges is not None else "uniform",
            "discretiser_mode": spec.config.discretiser, "n_states": int(disc.n_states),
            "learner": spec.config.agent, "n_tables": int(rows.shape[0]), "table": int(table), "ties": "first",
            "tied_states": int((n_max > 1).sum())}
    return meta, arrays


# ---- deep -----------------------------------------------------------------------------------------------
def _brax_network_defaults(agent: str) -> dict[str, Any]:
    """The activation and distribution jaxrobo's deep runs use: the defaults of Brax's network maker (jaxrobo's
    factory overrides only the layer widths, :func:`jaxrobo.deep.policy._factory`)."""
    import jax

    if agent == "ppo":
        from brax.training.agents.ppo import networks as nets

        maker = nets.make_ppo_networks
    else:
        from brax.training.agents.sac import networks as nets

        maker = nets.make_sac_networks
    params = inspect.signature(maker).parameters
    acts = {jax.nn.relu: "relu", jax.nn.swish: "swish"}
    activation = acts.get(params["activation"].default)
    distribution = params["distribution_type"].default if "distribution_type" in params else "tanh_normal"
    layer_norm = params["layer_norm"].default if "layer_norm" in params else False
    return {"activation": activation, "distribution": distribution, "layer_norm": layer_norm}


def deep_export(run_dir: str, cfg: dict[str, Any]) -> tuple[dict, dict]:
    """``(meta, arrays)`` of a PPO/SAC run's deterministic policy (see the module's docstring)."""
    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError

    where = os.path.join(run_dir, "config.yaml")
    spec = deep.spec_from_config(cfg, where)
    loaded = deep.load_policy(run_dir)
    net = loaded.net
    brax = _brax_network_defaults(net["agent"])
    if brax["activation"] is None or brax["distribution"] != "tanh_normal" or brax["layer_norm"]:
        raise ConfigError(f"{run_dir}: Brax's {net['agent']} networks use {brax}; the exporter knows relu/swish MLPs "
                          "with a tanh-Normal head and no layer norm")
    norm, policy = loaded.params[0], loaded.params[1]["params"]
    n_layers = len(policy)
    arrays: dict[str, np.ndarray] = {}
    sizes = []
    for i in range(n_layers):
        layer = policy.get(f"hidden_{i}")
        if layer is None:
            raise ConfigError(f"{os.path.join(run_dir, deep.POLICY_NPZ)}: no layer hidden_{i} of {n_layers}")
        arrays[f"kernel_{i}"] = np.asarray(layer["kernel"], np.float32)
        arrays[f"bias_{i}"] = np.asarray(layer["bias"], np.float32)
        sizes.append(int(arrays[f"bias_{i}"].shape[0]))
    if net["normalize_observations"]:
        arrays["obs_mean"] = np.asarray(norm.mean, np.float32)
        arrays["obs_std"] = np.asarray(norm.std, np.float32)
    space = spec.env.action_space()
    low, high = np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)
    # BraxEnv.scale_action: the action as is on a [-1, 1] box, else affine onto [low, high]
    unit = bool(np.all(low == -1.0) and np.all(high == 1.0))
    if not unit:
        arrays.update(action_low=low, action_high=high)
    obs_space = spec.env.observation_space()
    meta = {"format": 1, "kind": "mlp", "env_id": spec.env_id, "agent": net["agent"],
            "observation_size": int(net["observation_size"]),
            "observation_names": list(getattr(obs_space, "names", None) or []),
            "action_size": int(net["action_size"]), "action_names": list(getattr(space, "names", None) or []),
            "layer_sizes": sizes, "activation": brax["activation"], "distribution": "tanh_normal (mode: tanh(mean))",
            "normalize_observations": bool(net["normalize_observations"]),
            "action_scaling": "none" if unit else "affine"}
    return meta, arrays


def write_onnx(path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> bool:
    """``policy.onnx`` of an MLP export (input ``obs [n, d]`` float32, output ``action [n, action_size]``), the
    same computation as the numpy runner; False (nothing written) where the ``onnx`` package is missing."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        return False
    inits, nodes = [], []

    def const(name: str, value: np.ndarray) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    x = "obs"
    if meta["normalize_observations"]:
        nodes += [helper.make_node("Sub", [x, const("obs_mean", arrays["obs_mean"])], ["centred"]),
                  helper.make_node("Div", ["centred", const("obs_std", arrays["obs_std"])], ["normalised"])]
        x = "normalised"
    n = len(meta["layer_sizes"])
    for i in range(n):
        nodes += [helper.make_node("MatMul", [x, const(f"kernel_{i}", arrays[f"kernel_{i}"])], [f"mm_{i}"]),
                  helper.make_node("Add", [f"mm_{i}", const(f"bias_{i}", arrays[f"bias_{i}"])], [f"dense_{i}"])]
        x = f"dense_{i}"
        if i < n - 1:
            if meta["activation"] == "relu":
                nodes.append(helper.make_node("Relu", [x], [f"act_{i}"]))
            else:  # swish: x * sigmoid(x)
                nodes += [helper.make_node("Sigmoid", [x], [f"sig_{i}"]),
                          helper.make_node("Mul", [x, f"sig_{i}"], [f"act_{i}"])]
            x = f"act_{i}"
    a = int(meta["action_size"])
    nodes += [helper.make_node("Slice", [x, const("loc_start", np.array([0], np.int64)),
                                         const("loc_end", np.array([a], np.int64)),
                                         const("loc_axis", np.array([1], np.int64))], ["loc"]),
              helper.make_node("Tanh", ["loc"], ["unit_action" if meta["action_scaling"] == "affine" else "action"])]
    if meta["action_scaling"] == "affine":
        low, high = arrays["action_low"], arrays["action_high"]
        nodes += [helper.make_node("Add", ["unit_action", const("one", np.ones(1, np.float32))], ["shifted"]),
                  helper.make_node("Mul", ["shifted", const("half_range", (np.float32(0.5) * (high - low)))],
                                   ["scaled"]),
                  helper.make_node("Add", ["scaled", const("action_low", low)], ["action"])]
    graph = helper.make_graph(
        nodes, f"{meta['env_id']}_{meta['agent']}",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["n", int(meta["observation_size"])])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["n", a])], inits)
    model = helper.make_model(graph, producer_name="jaxrobo export", opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = min(model.ir_version, 8)
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return True


# ---- the runner ---------------------------------------------------------------------------------------------
#: The module an export's runner is made of, and the packages whose modules it writes into the same file.
RUNNER_MODULE, INLINED_PACKAGES = "jaxrobo.interop.numpy_policy", ("envs", "jaxrobo")


def _inlined(module: str | None) -> bool:
    return module is not None and module.split(".")[0] in INLINED_PACKAGES


def _top_names(tree: ast.Module) -> set[str]:
    """The names a module's own top-level statements bind (its imports aside)."""
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
    return names


def runner_source(root: str = RUNNER_MODULE) -> str:
    """``jaxrobo_policy.py``: the source of :mod:`jaxrobo.interop.numpy_policy` with the JAX-free task modules it
    imports (the Goto task's geometry and observation: :mod:`envs.quadcopter.geometry`,
    :mod:`envs.quadcopter.goto_step`; the cart-pole's command and observation: :mod:`envs.cartpole.rules`; the
    Python-float math they run on, :mod:`jaxrobo.core.scalar`) written in before it, dependencies first, as one module:
    the runner computes with the task's own functions and still needs nothing but numpy. A module so written in may be
    imported only by ``from module import name`` of names it defines at its top level (they share one namespace), and no
    two may define the same name: anything else is refused (``RuntimeError``), not written."""
    order: list[str] = []
    trees: dict[str, tuple[list[str], ast.Module]] = {}

    def visit(name: str) -> None:
        if name in trees:
            return
        spec = importlib.util.find_spec(name)
        with open(spec.origin) as f:
            text = f.read()
        trees[name] = (text.splitlines(), ast.parse(text))
        for node in ast.walk(trees[name][1]):
            if isinstance(node, ast.Import) and any(_inlined(a.name) for a in node.names):
                raise RuntimeError(f"{name}:{node.lineno}: the runner takes 'from module import name' only")
            if isinstance(node, ast.ImportFrom) and _inlined(node.module):
                if node not in trees[name][1].body:
                    raise RuntimeError(f"{name}:{node.lineno}: the runner takes module-level imports only")
                visit(node.module)
                missing = [a.name for a in node.names if a.asname or a.name not in _top_names(trees[node.module][1])]
                if missing:
                    raise RuntimeError(f"{name}:{node.lineno}: {', '.join(missing)} is not a name "
                                       f"{node.module} defines (or is renamed): it cannot share the runner's namespace")
        order.append(name)

    visit(root)
    seen: dict[str, str] = {}
    for name in order:
        for top in _top_names(trees[name][1]):
            if top in seen:
                raise RuntimeError(f"{top} is defined by both {seen[top]} and {name}: the runner is one namespace")
            seen[top] = name
    head, parts = "", []
    for name in order:
        lines, tree = trees[name]
        drop = set()
        for k, node in enumerate(tree.body):
            if k == 0 and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):  # the docstring
                if name == root:
                    head = "\n".join(lines[node.lineno - 1:node.end_lineno]) + "\n"
            elif not (isinstance(node, ast.ImportFrom) and (node.module == "__future__" or _inlined(node.module))):
                continue
            drop.update(range(node.lineno - 1, node.end_lineno))
        body = "\n".join(line for i, line in enumerate(lines) if i not in drop).strip("\n")
        owner = "the task" if name.split(".")[0] == "envs" else "jaxrobo"
        why = "" if name == root else f": {owner}'s own source, written in by jaxrobo export"
        parts.append(f"# ---- {name}{why} ----\n{body}")
    out = [head + "from __future__ import annotations"] + parts
    return "\n\n\n".join(out) + "\n"


# ---- the command ----------------------------------------------------------------------------------------
class _NoOnnx(Exception):
    """write_onnx wrote nothing: the temporary file is dropped, not moved into place."""


def export_run(run_dir: str, out: str, table: int | None = None, overwrite: bool = False,
               onnx: bool = True) -> dict[str, Any]:
    """Export the policy of ``run_dir`` into ``out`` (see the module's docstring); returns ``policy.json``'s
    content. Raises :class:`jaxrobo.core.config.ConfigError` before writing anything when the input is bad."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.core.version import __version__
    from jaxrobo.interop import numpy_policy

    from jaxrobo.io import rundir

    rundir.check_writable(out, "--out", directory=True)  # a file there or on the way: refused before any read
    if rundir.looks_like_run(out) or (os.path.isdir(out) and os.path.isdir(run_dir)
                                      and os.path.samefile(out, run_dir)):
        raise ConfigError(f"--out {out}: is a jaxrobo run directory; its policy files are the run's own: export "
                          "into a directory of its own")
    if os.path.isdir(out) and os.listdir(out) and not overwrite:
        raise ConfigError(f"--out {out}: not empty; pass --overwrite to replace what it holds")
    cfg = _check_run_dir(run_dir)
    agent = _agent(cfg, os.path.join(run_dir, "config.yaml"))
    from jaxrobo import deep

    if deep.is_deep(agent):
        if table is not None:
            raise ConfigError(f"--table: a {agent} run has one policy, no tables; drop the flag")
        meta, arrays = deep_export(run_dir, cfg)
    else:
        meta, arrays = tabular_export(run_dir, cfg, table)
    # The observation the policy expects is the env's, as this run configured it (e.g. a cart-pole run with
    # round_obs rounds its observations to 0.1 before the policy sees them): the env's settings go with the policy.
    meta["env_options"] = dict(cfg.get("env_options") or {})
    meta["env_params"] = dict(cfg.get("env_params") or {})
    meta["source"] = {"run": os.path.abspath(run_dir), "jaxrobo_version": __version__}
    # What a policy driving the robot needs of the task besides the policy (control period, observation
    # constants, action table), for tasks with a native port: the ROS policy node works from the export alone
    from jaxrobo.ros.bridge import robot_section

    section = robot_section(meta)
    if section is not None:
        meta["robot"] = section
    os.makedirs(out, exist_ok=True)
    # Each file replaced atomically (a kill leaves the previous export's file or the new one, never none or a torn
    # one); policy.json last, so that it never describes arrays that are not there yet.
    rundir.atomic_write(os.path.join(out, numpy_policy.POLICY_NPZ), lambda f: np.savez_compressed(f, **arrays))
    runner = runner_source().encode()
    rundir.atomic_write(os.path.join(out, RUNNER_NAME), lambda f: f.write(runner))
    onnx_path = os.path.join(out, "policy.onnx")
    wrote_onnx = False
    if meta["kind"] == "mlp":
        if onnx:
            try:
                with rundir.atomic_path(onnx_path, suffix=".onnx") as tmp:
                    wrote_onnx = write_onnx(tmp, meta, arrays)
                    if not wrote_onnx:  # no onnx package: nothing to put in place
                        raise _NoOnnx
            except _NoOnnx:
                pass
        meta["onnx"] = wrote_onnx
    if not wrote_onnx and os.path.lexists(onnx_path):  # a previous export's network, not this one
        os.remove(onnx_path)
    rundir.atomic_write_json(os.path.join(out, numpy_policy.POLICY_JSON), meta)
    return meta
