"""Every bad input is refused at the boundary: a clear message naming the field, exit code 2 (or the error for a
Python call), no traceback, nothing written, nothing compiled or trained.

One table, :data:`CASES`. A case is a command (``train``, ``sweep``, ``plot``, ``show``, ``eval``, ``export``,
``list`` - run in-process through ``jaxrobo.cli.main`` - or ``api``, a Python call), its arguments, the message
fragment that must appear, and optionally a ``setup`` that writes the input files (a broken run directory, a broken
YAML) first. ``{tmp}`` in an argument is the case's own temporary directory. To cover a new command, add its cases
with its name: the runner is the same.

Training, sweeping, flying and drawing are replaced for this module by functions that fail the test, so a case
that got past validation cannot pass by accident (and none compiles: the whole file runs in seconds).
"""
from __future__ import annotations

import dataclasses
import os
import pickle  # noqa: F401  (the pickled-npz case writes an object array, which needs pickle)
from typing import Any, Callable

import numpy as np
import pytest

from jaxrobo.cli import main
from jaxrobo.core.config import ConfigError, load_yaml, parse_overrides

CP = "CartPoleStayUp-v0"
GOTO = "QuadcopterGoto-v1"
GOTO2 = "QuadcopterGoto-v2"  # its default discretiser is of edges (edges_0..edges_7)


@dataclasses.dataclass(frozen=True)
class Case:
    id: str
    command: str  # train | sweep | plot | show | list | api
    args: tuple = ()  # argv after the command; for "api", a callable(tmp) that must raise
    fragment: str = ""  # must appear in stderr (CLI) or in the error message (api)
    setup: Callable[[str, Any], None] | None = None  # setup(tmp, monkeypatch): write input files first
    code: int = 2  # expected exit code (list survives a broken agent YAML with 0 and a note)
    out: bool = True  # train/sweep: append --out {tmp}/out (not for a --resume case, which refuses --out)


# ---- input builders -------------------------------------------------------------------------------------------
_GOTO_CONFIG: dict[str, Any] = {}


def goto_config() -> dict[str, Any]:
    """A valid QuadcopterGoto-v1 run config (as `jaxrobo train` writes it), built once."""
    if not _GOTO_CONFIG:
        from jaxrobo.training.run import resolve

        _GOTO_CONFIG.update(resolve(GOTO, check_memory=False).to_dict())
    return _GOTO_CONFIG


def write_run(tmp: str, name: str = "run", config: Any = "goto", q: Any = "ok", npz: bytes | None = None,
              config_text: str | None = None) -> str:
    """A run directory with config.yaml and qtables.npz; each part can be broken or left out (None)."""
    import yaml

    d = os.path.join(tmp, name)
    os.makedirs(d, exist_ok=True)
    if config_text is not None:
        with open(os.path.join(d, "config.yaml"), "w") as f:
            f.write(config_text)
    elif config is not None:
        cfg = goto_config() if config == "goto" else config
        with open(os.path.join(d, "config.yaml"), "w") as f:
            yaml.safe_dump(cfg, f, sort_keys=False)
    path = os.path.join(d, "qtables.npz")
    if npz is not None:
        with open(path, "wb") as f:
            f.write(npz)
    elif isinstance(q, str) and q == "ok":
        np.savez(path, **saved_tables(GOTO))  # the Goto default preset: 1296 states, 5 actions
    elif q is not None:  # a dict: those arrays alone; an array: q beside the Goto default discretiser's arrays
        np.savez(path, **q) if isinstance(q, dict) else np.savez(path, **{**saved_tables(GOTO), "q": q})
    return d


_SAVED: dict[str, dict[str, np.ndarray]] = {}


def saved_tables(env_id: str) -> dict[str, np.ndarray]:
    """The arrays of a one-table ``qtables.npz`` of ``env_id``'s default preset as `jaxrobo train` writes them: ``q``
    (zeros) and the discretiser's (``low``, ``width``, ``bins``, ``edges_<i>``), built once."""
    if env_id not in _SAVED:
        from jaxrobo.io.results import discretiser_arrays
        from jaxrobo.training.run import resolve
        from jaxrobo.training.trainer import make_discretiser_for

        spec = resolve(env_id, check_memory=False)
        disc = make_discretiser_for(spec.env, spec.config)
        _SAVED[env_id] = {"q": np.zeros((1, 1, disc.n_states, spec.env.num_actions), np.float32),
                          **discretiser_arrays(disc)}
    return _SAVED[env_id]


def tampered(env_id: str = GOTO, **changes: Any) -> Callable[[str, Any], None]:
    """A run of ``env_id``'s default config whose ``qtables.npz`` has ``changes``: an array, None (left out), or a
    function of the saved array."""
    def setup(tmp: str, _mp: Any) -> None:
        arrays = dict(saved_tables(env_id))
        for name, change in changes.items():
            if change is None:
                arrays.pop(name)
            else:
                arrays[name] = change(arrays[name]) if callable(change) else change
        from jaxrobo.training.run import resolve

        config = goto_config() if env_id == GOTO else resolve(env_id, check_memory=False).to_dict()
        d = write_run(tmp, config=config, q=arrays)
        with open(os.path.join(d, "status.json"), "w") as f:
            f.write('{"status": "complete"}')  # a finished run: export reads no other
    return setup


def nudged(i: int, by: float) -> Callable[[np.ndarray], np.ndarray]:
    """The array with its ``i``-th value moved by ``by``, its dtype kept."""
    def change(x: np.ndarray) -> np.ndarray:
        x = x.copy()
        x[i] = x[i] + by
        return x
    return change


def ok_npz_bytes(tmp: str) -> bytes:
    path = os.path.join(tmp, "_ok.npz")
    np.savez(path, q=np.zeros((1, 1, 1296, 5), np.float32))
    data = open(path, "rb").read()
    os.remove(path)
    return data


def pickled_npz_bytes(tmp: str) -> bytes:
    path = os.path.join(tmp, "_p.npz")
    np.savez(path, q=np.array([{"evil": 1}], dtype=object))
    data = open(path, "rb").read()
    os.remove(path)
    return data


STATS_HEADER = ("episode,return_mean,return_std,return_p10,return_p50,return_p90,length_mean,length_std,"
                "length_p10,length_p50,length_p90,epsilon\n")
STATS_ROW = "0,1,0,1,1,1,5,0,5,5,5,0.1\n"


def write_csv_run(tmp: str, name: str, filename: str, text: str | bytes) -> None:
    d = os.path.join(tmp, name)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, filename), "wb") as f:
        f.write(text.encode() if isinstance(text, str) else text)


def agent_yaml(text: str, env_id: str = CP, which: str = "agent_config") -> Callable[[str, Any], None]:
    """Point ``env_id``'s agent (or env) YAML at a file holding ``text`` for this case only."""
    def setup(tmp: str, monkeypatch: Any) -> None:
        from jaxrobo.task import registry

        path = os.path.join(tmp, "cfg", "bad.yaml")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
        reg = registry._lookup(env_id)
        spec = dataclasses.replace(reg.spec, **{which: path})
        monkeypatch.setitem(registry._REGISTRY, env_id, dataclasses.replace(reg, spec=spec))
    return setup


#: Hostile config.yaml texts, as classes: an alias bomb, nesting past the limit, a file past the size cap, bytes
#: that are not UTF-8, NUL bytes, an env_id that names a module (which must never be imported).
ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n"
    for i in range(8))
DEEP = "env_id: " + "[" * 5000 + "]" * 5000 + "\n"
HUGE = "env_id: [" + "1, " * 600_000 + "1]\n"
EVIL = "evil_jaxrobo_module"


def evil_module(tmp: str, monkeypatch: Any) -> None:
    """A module that, if imported, leaves a file behind (the runner then sees a file written)."""
    with open(os.path.join(tmp, f"{EVIL}.py"), "w") as f:
        f.write("import os\nopen(os.path.join(os.path.dirname(__file__), 'IMPORTED'), 'w').write('pwned')\n")
    monkeypatch.syspath_prepend(tmp)


def resumable(config_text: str | bytes | None = None, config: Any = None, env: bool = False
              ) -> Callable[[str, Any], None]:
    """An interrupted train run directory ({tmp}/run: a checkpoint, an interrupted status) whose config.yaml is
    ``config_text`` or ``config``; ``env`` also writes the module an env_id may name."""
    def setup(tmp: str, monkeypatch: Any) -> None:
        import json

        import yaml

        d = os.path.join(tmp, "run")
        os.makedirs(d)
        with open(os.path.join(d, "checkpoint.npz"), "wb") as f:
            f.write(b"not read before the config")
        with open(os.path.join(d, "status.json"), "w") as f:
            json.dump({"status": "interrupted"}, f)
        text = config_text if config_text is not None else yaml.safe_dump(config)
        with open(os.path.join(d, "config.yaml"), "wb") as f:
            f.write(text.encode() if isinstance(text, str) else text)
        if env:
            evil_module(tmp, monkeypatch)
    return setup


def cp_config(**changes: Any) -> dict[str, Any]:
    from jaxrobo.training.run import resolve

    return {**resolve(CP, check_memory=False).to_dict(), **changes}


def interrupted_sweep(env_id: str, **flags: Any) -> Callable[[str, Any], None]:
    """An interrupted sweep ({tmp}/sw) whose saved flags name ``env_id`` (and ``flags``)."""
    def setup(tmp: str, monkeypatch: Any) -> None:
        import json

        from jaxrobo.training.sweep.cli import SWEEP_FLAGS

        d = os.path.join(tmp, "sw")
        os.makedirs(d)
        with open(os.path.join(d, "checkpoint.npz"), "wb") as f:
            f.write(b"x")
        with open(os.path.join(d, "status.json"), "w") as f:
            json.dump({"status": "interrupted", "out": "/somewhere/else"}, f)
        with open(os.path.join(d, "sweep_state.json"), "w") as f:
            json.dump({"format": 1, "extra": {"flags": {**SWEEP_FLAGS, "env": env_id, **flags}, "argv": []}}, f)
        evil_module(tmp, monkeypatch)
    return setup


def setenv(**values: str) -> Callable[[str, Any], None]:
    def setup(_tmp: str, monkeypatch: Any) -> None:
        for k, v in values.items():
            monkeypatch.setenv(k, v)
    return setup


def out_link(target: str) -> Callable[[str, Any], None]:
    """{tmp}/out as a symlink to ``target`` ({tmp}-relative; "out" itself: a loop)."""
    return lambda tmp, _mp: os.symlink(os.path.join(tmp, target), os.path.join(tmp, "out"))


def forged_npz(tmp: str, shape_prefix: str = "1099511627776, ") -> bytes:
    """qtables.npz whose q header claims 2^40 more rows than its data holds (a correct zip CRC)."""
    import io
    import zipfile

    raw = ok_npz_bytes(tmp)
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        blob = z.read("q.npy")
    hlen = int.from_bytes(blob[8:10], "little")
    header = blob[10:10 + hlen].decode("latin1").strip().replace("'shape': (", "'shape': (" + shape_prefix)
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    forged = blob[:8] + len(header).to_bytes(2, "little") + header.encode("latin1") + blob[10 + hlen:]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("q.npy", forged)
    return buf.getvalue()


def flipped_npz(tmp: str) -> bytes:
    data = bytearray(ok_npz_bytes(tmp))
    data[len(data) // 2] ^= 0xFF  # in the table's data: the zip's CRC no longer matches
    return bytes(data)


def run_dir(**kw: Any) -> Callable[[str, Any], None]:
    return lambda tmp, _mp: write_run(tmp, **kw)


def raises(fn: Callable[[], Any]) -> Callable[[str], Any]:
    return lambda tmp: fn()


# ---- the table --------------------------------------------------------------------------------------------------
def T(id: str, fragment: str, *argv: str, setup=None) -> Case:  # noqa: N802 - a table row
    return Case(f"train-{id}", "train", argv, fragment, setup)


TRAIN = [
    # argparse's type errors: one line (jaxrobo.core.cliargs.Parser), not the usage block
    T("n-envs-not-int", "jaxrobo train: argument --n-envs: invalid int value: 'abc'", "--n-envs", "abc"),
    T("nepisodes-nan", "jaxrobo train: argument --nepisodes: invalid int value: 'nan'", "--nepisodes", "nan"),
    T("total-steps-float", "jaxrobo train: argument --total-steps: invalid int value: '1e20'",
      "--total-steps", "1e20"),
    T("unrecognized-flag", "jaxrobo train: unrecognized arguments: --nenvs 4", "--nenvs", "4"),
    # unknown keys and ids
    T("unknown-key", "unknown key 'alfa' (did you mean alpha", "--set", "alfa=0.1"),
    T("unknown-env-key", "unknown key 'nope'", "--set", "env.nope=1"),
    T("unknown-agent-key", "unknown key 'pos_step'", "--set", "agent.pos_step=1"),
    T("typo-env-param", "unknown key 'pos_stepp'", "--set", "pos_stepp=0.1"),
    T("other-task-key", "unknown key 'max_altitude'", "--set", "max_altitude=3"),
    T("unknown-env-id", "environment id: unknown key 'Nope-v0'", "--env", "Nope-v0"),
    T("env-id-typo", "did you mean CartPoleStayUp-v0", "--env", "CartPoleStayUp-v2"),
    T("unknown-preset", "preset='fast': allowed values are default, seed", "--preset", "fast"),
    # --set syntax
    T("set-no-equals", "--set 'alpha': expected KEY=VALUE", "--set", "alpha"),
    T("set-empty-key", "the key is empty", "--set", "=3"),
    T("set-twice", "--set alpha: given twice", "--set", "alpha=0.1", "--set", "alpha=0.2"),
    T("set-bad-yaml", "--set alpha: not valid YAML", "--set", "alpha=[1"),
    T("set-python-tag", "could not determine a constructor", "--set", "alpha=!!python/object/apply:os.system [ls]"),
    T("set-duplicate-key", "duplicate key 'a'", "--set", "alpha={a: 1, a: 2}"),
    T("set-mapping-for-number", "alpha={'a': 1}: expected a number", "--set", "alpha={a: 1}"),
    # flags against --set: refused, neither silently wins
    T("n-envs-clash", "n_envs given twice: --n-envs 2 and --set n_envs=3", "--n-envs", "2", "--set", "n_envs=3"),
    T("seed-clash", "seed given twice", "--seed", "2", "--set", "seed=3"),
    T("nepisodes-clash", "nepisodes given twice: --nepisodes 2 and --set agent.nepisodes=3", "--nepisodes", "2",
      "--set", "agent.nepisodes=3"),
    T("agent-clash", "agent given twice", "--agent", "sarsa", "--set", "agent=qlearn"),
    # floats: range, type, finiteness
    T("alpha-high", "alpha=1.5: expected a number > 0.0 and <= 1.0", "--set", "alpha=1.5"),
    T("alpha-zero", "alpha=0.0: expected a number > 0.0", "--set", "alpha=0"),
    T("alpha-tiny-exponent-ok-but-negative", "alpha=-0.001: expected a number > 0.0", "--set", "alpha=-1e-3"),
    T("alpha-string", "alpha='abc': expected a number", "--set", "alpha=abc"),
    T("alpha-nan", "alpha=nan: must be finite", "--set", "alpha=.nan"),
    T("alpha-overflow", "alpha=inf: must be finite", "--set", "alpha=1e400"),
    T("alpha-list", "alpha=[0.1]: expected a number", "--set", "alpha=[0.1]"),
    T("alpha-bool", "alpha=True: expected a number", "--set", "alpha=true"),
    # integers no config holds: past Python's 4,300 digits (PyYAML's conversion raises), past 64 bits (past
    # float's range where they become floats, unprintable in a message)
    T("seed-5000-digits", "--set seed: holds an integer too long to read", "--set", "seed=" + "9" * 5000),
    T("seed-hex-20000-bits", "--set seed: an integer of 20,000 bits", "--set", "seed=0x" + "f" * 5000),
    T("alpha-int-past-float", "--set alpha: an integer of 1,326 bits", "--set", "alpha=" + "1" * 400),
    T("state-low-int-past-float", "--set state_low: an integer of 1,326 bits", "--set",
      "state_low=[1, " + "1" * 400 + "]"),
    T("gamma-negative", "gamma=-0.1: expected a number >= 0.0 and <= 1.0", "--set", "gamma=-0.1"),
    T("gamma-high", "gamma=1.01", "--set", "gamma=1.01"),
    T("epsilon-high", "epsilon=2", "--set", "epsilon=2"),
    T("epsilon-discount-zero", "epsilon_discount=0.0: expected a number > 0.0", "--set", "epsilon_discount=0"),
    T("epsilon-min-negative", "epsilon_min=-1", "--set", "epsilon_min=-1"),
    T("resolution-zero", "resolution=0.0: expected a number > 0.0", "--set", "resolution=0"),
    # integers: range, type, int32
    T("n-envs-zero-set", "n_envs=0: expected an integer >= 1", "--set", "n_envs=0"),
    T("n-envs-fraction", "n_envs=2.5: expected an integer", "--set", "n_envs=2.5"),
    T("n-envs-string", "n_envs='abc': expected an integer", "--set", "n_envs=abc"),
    T("n-envs-bool", "n_envs=True: expected an integer", "--set", "n_envs=true"),
    T("n-envs-int32", "n_envs=3000000000: expected an integer >= 1 and <= 2147483647", "--set", "n_envs=3000000000"),
    T("n-envs-flag-zero", "n_envs=0: expected an integer >= 1", "--n-envs", "0"),
    T("n-envs-flag-not-int", "argument --n-envs: invalid int value: 'abc'", "--n-envs", "abc"),
    T("seed-negative", "seed=-1: expected an integer >= 0 and <= 2147483647", "--seed", "-1"),
    T("seed-int64-overflow", "seed=99999999999999999999: expected an integer >= 0 and <= 2147483647", "--seed",
      "99999999999999999999"),
    T("seed-int32-overflow", "seed=2147483648", "--seed", "2147483648"),
    T("seed-fraction", "seed=1.5: expected an integer", "--set", "seed=1.5"),
    T("nepisodes-zero", "nepisodes=0: expected an integer >= 1", "--nepisodes", "0"),
    T("nepisodes-negative", "nepisodes=-3", "--nepisodes", "-3"),
    T("nsteps-zero", "nsteps=0: expected an integer >= 1", "--set", "nsteps=0"),
    T("nsteps-int32", "nsteps=99999999999: expected an integer >= 1 and <= 2147483647", "--set", "nsteps=99999999999"),
    T("nsteps-inf", "nsteps=inf: expected an integer", "--set", "nsteps=1e400"),
    T("nsteps-exponent-int32", "nsteps=10000000000: expected an integer", "--set", "nsteps=1e10"),
    T("steps-product-int32", "nepisodes x nsteps = 100000 x 100000 = 10,000,000,000 steps per env: must be <=",
      "--nepisodes", "100000", "--set", "nsteps=100000"),
    T("chunk-steps-zero", "chunk_steps=0: expected an integer >= 1", "--set", "chunk_steps=0"),
    T("eval-episodes-negative", "eval_episodes=-1: expected an integer >= 0", "--set", "eval_episodes=-1"),
    T("eval-envs-zero", "eval_envs=0: expected an integer >= 1", "--set", "eval_envs=0"),
    T("env-group-negative", "env_group=-1: expected an integer >= 0", "--set", "env_group=-1"),
    T("max-episode-steps-zero", "max_episode_steps=0: expected an integer >= 1", "--set", "env.max_episode_steps=0"),
    T("max-episode-steps-int32", "max_episode_steps=99999999999", "--set", "env.max_episode_steps=99999999999"),
    # booleans and choices
    T("record-episodes-not-bool", "record_episodes='maybe': expected a boolean", "--set", "record_episodes=maybe"),
    T("shared-table-int", "shared_table=1: expected a boolean", "--set", "shared_table=1"),
    T("seed-compat-not-bool", "seed_compat='sure': expected a boolean", "--set", "seed_compat=sure"),
    T("agent-flag-unknown", "agent='dqn': allowed values are 'qlearn', 'sarsa', 'expected_sarsa', 'double_q'",
      "--agent", "dqn"),
    T("agent-set-unknown", "agent='dqn': allowed values are", "--set", "agent=dqn"),
    T("discretiser-unknown", "discretiser='hash': allowed values are 'bins', 'round', 'edges'", "--set",
      "discretiser=hash"),
    T("control-type-unknown", "control_type='magic': allowed values are", "--set", "control_type=magic"),
    T("n-actions-unsupported", "n_actions=3: allowed values are 2, 4", "--set", "n_actions=3"),
    T("fused-unknown", "fused='fast': allowed values are 'auto', 'off', 'xla', 'pallas'", "--set", "fused=fast"),
    T("fused-pallas-unsupported", "ExecutionPlan fused='pallas': backend='mjx'; only backend='analytic'",
      "--set", "fused=pallas", "--set", "env.backend=mjx"),
    T("running-step-off-grid", "running_step=0.0333 s is not a whole multiple of the physics timestep",
      "--set", "running_step=0.0333"),
    T("timestep-tiny", "timestep=1e-12 s: running_step=0.04 s would take 4e+10 physics steps per control step; "
      "expected at most 100,000", "--set", "timestep=1e-12"),
    # combinations
    T("double-q-seed-compat", "agent='double_q' with seed_compat=true: the seed's learners had one table",
      "--agent", "double_q", "--set", "seed_compat=true"),
    T("double-q-seed-preset", "agent='double_q' with seed_compat=true", "--preset", "seed", "--agent", "double_q"),
    T("number-splits-ignored", "number_splits=20 would be ignored: bins=[1, 6, 8, 10] is given (set bins=null",
      "--set", "number_splits=20"),
    T("edges-ignored", "edges=[[0], [0], [0], [0]] would be ignored: discretiser='bins' does not use it",
      "--set", "edges=[[0], [0], [0], [0]]"),
    T("resolution-ignored", "resolution=0.5 would be ignored: discretiser='bins' does not use it",
      "--set", "resolution=0.5"),
    T("bins-ignored-in-round", "bins=[1, 2, 3, 4] would be ignored: discretiser='round' does not use it",
      "--preset", "seed", "--set", "bins=[1, 2, 3, 4]"),
    # discretiser settings
    T("number-splits-zero", "number_splits=0: expected an integer >= 1", "--set", "number_splits=0"),
    T("number-splits-above-range", "number_splits=10001: expected an integer >= 1 and <= 10000", "--set", "bins=null",
      "--set", "number_splits=10001"),
    T("number-splits-state-overflow", "number_splits=10000: 10000 x 10000 x 10000 x 10000 = 1e+16 states, more than",
      "--set", "bins=null", "--set", "number_splits=10000"),
    T("bins-short", "bins=[1, 2, 3]: expected 4 bin counts, one per observation dimension, got 3", "--set",
      "bins=[1, 2, 3]"),
    T("bins-long", "expected 4 bin counts, one per observation dimension, got 5", "--set", "bins=[1, 2, 3, 4, 5]"),
    T("bins-empty", "expected 4 bin counts", "--set", "bins=[]"),
    T("bins-zero", "bins[2]=0: expected an integer >= 1", "--set", "bins=[1, 6, 0, 10]"),
    T("bins-negative", "bins[2]=-2: expected an integer >= 1", "--set", "bins=[1, 6, -2, 10]"),
    T("bins-fraction", "bins[2]=2.5: expected an integer >= 1", "--set", "bins=[1, 6, 2.5, 10]"),
    T("bins-string-entry", "bins[2]='a': expected an integer >= 1", "--set", "bins=[1, 6, a, 10]"),
    T("bins-bool-entry", "bins[2]=True: expected an integer >= 1", "--set", "bins=[1, 6, true, 10]"),
    T("bins-nested", "bins[0]=[1]: expected an integer >= 1", "--set", "bins=[[1], [2], [3], [4]]"),
    T("bins-scalar", "bins=5: expected a list or null", "--set", "bins=5"),
    T("bins-state-overflow", "bins=[100000, 100000, 1, 1]: 100000 x 100000 x 1 x 1 = 1e+10 states", "--set",
      "bins=[100000, 100000, 1, 1]"),
    T("state-low-short", "state_low=[0, 0, 0]: expected 4 values, one per observation dimension, got 3", "--set",
      "state_low=[0, 0, 0]"),
    T("state-high-long", "state_high=[1, 1, 1, 1, 1]: expected 4 values", "--set", "state_high=[1, 1, 1, 1, 1]"),
    T("state-high-below-low", "state_high[2]=-1 must be greater than state_low[2]=-1", "--set",
      "state_low=[-1, -1, -1, -1]", "--set", "state_high=[1, 1, -1, 1]"),
    T("state-equal", "state_high[0]=0 must be greater than state_low[0]=0", "--set", "state_low=[0, 0, 0, 0]",
      "--set", "state_high=[0, 1, 1, 1]"),
    T("state-high-below-task-low", "state_high[0]=-10 must be greater than state_low[0]=-2.4", "--set",
      "state_high=[-10, 1, 1, 1]"),
    T("state-low-string", "state_low=[0, 0, 'a', 0]: expected a list of numbers", "--set", "state_low=[0, 0, a, 0]"),
    T("state-low-inf", "every value must be finite", "--set", "state_low=[0, 0, .inf, 0]"),
    T("state-low-scalar", "state_low=5: expected a list or null", "--set", "state_low=5"),
    T("edges-missing", "discretiser='edges' needs edges: one list of edges per dimension (4 lists", "--set",
      "discretiser=edges"),
    T("edges-short", "one list of edges per dimension (4 lists", "--set", "discretiser=edges", "--set",
      "edges=[[0], [0], [0]]"),
    T("edges-unsorted", "edges[0]=[1.0, 0.0]: edges must be strictly increasing", "--set", "discretiser=edges",
      "--set", "edges=[[1, 0], [0], [0], [0]]"),
    T("edges-repeated", "edges[0]=[0.0, 0.0]: edges must be strictly increasing", "--set", "discretiser=edges",
      "--set", "edges=[[0, 0], [0], [0], [0]]"),
    T("edges-not-numbers", "edges[0]=['a']: expected a list of numbers", "--set", "discretiser=edges", "--set",
      "edges=[[a], [0], [0], [0]]"),
    T("edges-flat", "edges[0]=0: expected a list of numbers", "--set", "discretiser=edges", "--set",
      "edges=[0, 0, 0, 0]"),
    T("edges-nan", "edges[0]=[nan]: every edge must be finite", "--set", "discretiser=edges", "--set",
      "edges=[[.nan], [0], [0], [0]]"),
    T("round-resolution-tiny", "resolution=1e-09: gives", "--preset", "seed", "--set", "resolution=1e-9"),
    # memory
    T("n-envs-huge", "n_envs=1000000000: the batch needs at least", "--n-envs", "1000000000"),
    T("tables-huge", "the batch needs at least", "--set", "bins=null", "--set", "number_splits=120"),
    T("records-huge", "nepisodes=1000000 recorded) but", "--n-envs", "100000", "--nepisodes", "1000000",
      "--set", "nsteps=10"),
    # other tasks
    T("goto-n-obstacles", "n_obstacles=33: expected an integer >= 0 and <= 32", "--env", GOTO, "--set",
      "n_obstacles=33"),
    T("goto-obstacle-kind", "obstacle_kind='triangle': allowed values are", "--env", GOTO, "--set",
      "obstacle_kind=triangle"),
    T("goto-backend", "backend='warp': allowed values are", "--env", GOTO, "--set", "backend=warp"),
    T("goto-goal-tolerance", "goal_tolerance=-1.0: expected a number > 0.0", "--env", GOTO, "--set",
      "goal_tolerance=-1"),
    T("goto-bins-short", "bins=[2, 9, 3]: expected 7 bin counts", "--env", GOTO, "--set", "bins=[2, 9, 3]"),
    T("liveshow-double-q-seed", "agent='double_q' with seed_compat=true", "--env", "QuadcopterLiveShow-v0",
      "--preset", "seed", "--set", "agent=double_q"),
    # broken YAML files behind the presets
    T("agent-yaml-malformed", "not valid YAML", setup=agent_yaml("default: [1, 2\n")),
    T("agent-yaml-python-tag", "could not determine a constructor",
      setup=agent_yaml("default: !!python/object/apply:os.system ['echo pwned']\n")),
    T("agent-yaml-preset-not-mapping", "preset 'default' must be a mapping of key: value, got list",
      setup=agent_yaml("default: [1, 2]\n")),
    T("agent-yaml-top-level-list", "expected a mapping of key: value at the top level, got list",
      setup=agent_yaml("- 1\n- 2\n")),
    T("agent-yaml-duplicate-key", "duplicate key 'alpha' (lines 2 and 3)",
      setup=agent_yaml("default:\n  alpha: 0.1\n  alpha: 0.2\n")),
    T("agent-yaml-env-not-mapping", "preset 'default': env must be a mapping",
      setup=agent_yaml("default:\n  env: 3\n")),
    T("agent-yaml-unknown-key", "unknown key 'alfa'", setup=agent_yaml("default:\n  alfa: 0.1\n")),
    T("agent-yaml-out-of-range", "alpha=5.0: expected a number > 0.0", setup=agent_yaml("default:\n  alpha: 5\n")),
    T("agent-yaml-non-string-key", "unknown key '1'", setup=agent_yaml("default:\n  1: 2\n")),
    T("env-yaml-not-mapping", "expected a mapping of key: value, got list",
      setup=agent_yaml("env: [1, 2]\n", which="config")),
    T("env-yaml-duplicate-key", "duplicate key 'pos_step'",
      setup=agent_yaml("env:\n  pos_step: 0.1\n  pos_step: 0.2\n", which="config")),
    # floats that are 0, subnormal or inf in float32 (the precision a run computes in)
    T("alpha-float32-zero", "alpha=1e-320: is 0 in float32", "--set", "alpha=1e-320"),
    T("alpha-float32-subnormal", "alpha=1e-40: is 0 in float32", "--set", "alpha=1e-40"),
    T("env-param-float32-zero", "pos_step=1e-45: is 0 in float32", "--set", "pos_step=1e-45"),
    T("resolution-float32-inf", "resolution=1e+39: is inf in float32", "--preset", "seed", "--set",
      "resolution=1e39"),
    T("state-bound-float32-inf", "a value is inf in float32", "--set", "state_high=[1e39, 1, 1, 1]"),
    # --out that cannot be a run directory
    T("eval-episodes-huge", "eval_episodes=1000000000: too many greedy evaluation episodes",
      "--set", "eval_episodes=1000000000", "--set", "eval_envs=1"),
    T("eval-episodes-memory", "eval_episodes=2000000: the greedy evaluation of 1 table(s) x 2,000,000 episodes",
      "--set", "eval_episodes=2000000", "--set", "eval_envs=1", "--set", "nsteps=1000"),
    T("out-symlink-loop", "--out {tmp}/out: a symlink loop", setup=out_link("out")),
    T("out-dangling-symlink", "--out {tmp}/out: is a dangling symlink", setup=out_link("nowhere")),
    # --resume of a run directory whose config.yaml is hostile: refused before parsing it all, nothing imported
    Case("train-resume-alias-bomb", "train", ("--resume", "{tmp}/run"), "YAML aliases (*name) are not accepted",
         resumable(ALIAS_BOMB), out=False),
    Case("train-resume-deep-nesting", "train", ("--resume", "{tmp}/run"), "nested deeper than 32 levels",
         resumable(DEEP), out=False),
    Case("train-resume-huge-config", "train", ("--resume", "{tmp}/run"), "more than a config holds",
         resumable(HUGE), out=False),
    Case("train-resume-binary-config", "train", ("--resume", "{tmp}/run"), "cannot be read as a text file (not UTF-8",
         resumable(b"env_id: \xff\xfe\x00\x81"), out=False),
    Case("train-resume-nul-config", "train", ("--resume", "{tmp}/run"), "holds NUL bytes",
         resumable("env_id: a\0b\n"), out=False),
    Case("train-resume-not-mapping", "train", ("--resume", "{tmp}/run"), "expected a mapping of key: value",
         resumable("- 1\n"), out=False),
    Case("train-resume-module-env-id", "train", ("--resume", "{tmp}/run"),
         f"names the Python module '{EVIL}', which a file read back never imports", 
         resumable(config=cp_config(env_id=f"{EVIL}:Foo-v0"), env=True), out=False),
    Case("train-resume-other-env", "train", ("--resume", "{tmp}/run", "--env", GOTO),
         f"is of env_id '{CP}'; with --resume, --env only confirms", resumable(config=cp_config()), out=False),
    Case("train-resume-missing", "train", ("--resume", "{tmp}/nope"), "--resume {tmp}/nope: no such run directory",
         out=False),
    Case("train-resume-a-file", "train", ("--resume", "{tmp}/f"), "--resume {tmp}/f: is an existing file, not a run "
         "directory; give the directory of the run to go on with", lambda tmp, mp: open(f"{tmp}/f", "w").close(),
         out=False),
    # a key the env does not have (an env_id edited to another task's) is named as config.yaml's, not as a --set
    Case("train-resume-config-unknown-key", "train", ("--resume", "{tmp}/run"),
         "--resume {tmp}/run: config.yaml: unknown key '", resumable(config=cp_config(env_id="ArmReach-v0")),
         out=False),
]

SWEEP = [Case(f"sweep-{i}", "sweep", a, f) for i, a, f in [
    ("seeds-not-int", ("--seeds", "x"), "jaxrobo sweep: argument --seeds: invalid int value: 'x'"),
    ("seeds-zero", ("--seeds", "0"), "--seeds 0: must be >= 1"),
    ("eval-episodes-negative", ("--eval-episodes", "-1"), "--eval-episodes -1: must be >= 0"),
    ("eval-metric-without-eval", ("--metric", "eval_mean_length", "--eval-episodes", "0"),
     "--metric eval_mean_length: needs --eval-episodes > 0"),
    ("metric-unknown", ("--metric", "bogus"), "argument --metric: invalid choice: 'bogus'"),
    ("grid-no-equals", ("--grid", "alpha"), "--grid 'alpha': expected KEY=V1,V2,..."),
    ("grid-no-values", ("--grid", "alpha="), "no values after '='"),
    ("grid-seed", ("--grid", "seed=1,2"), "the seed is not a swept parameter"),
    ("grid-unknown-key", ("--grid", "alfa=0.1,0.2"), "unknown key 'alfa'"),
    ("grid-out-of-range", ("--grid", "alpha=5,0.1"), "alpha=5.0: expected a number > 0.0 and <= 1.0"),
    ("range-malformed", ("--random", "2", "--range", "alpha=0.1"), "expected KEY=LOW:HIGH"),
    ("range-reversed", ("--random", "2", "--range", "alpha=0.9:0.1"), "need LOW < HIGH"),
    ("range-without-random", ("--range", "alpha=0.1:0.9"), "--range needs --random N"),
    ("random-without-range", ("--random", "3"), "--random N needs at least one --range"),
    ("set-out-of-range", ("--set", "alpha=7"), "alpha=7.0: expected a number > 0.0 and <= 1.0"),
    ("n-envs-zero", ("--n-envs", "0"), "n_envs=0: expected an integer >= 1"),
    ("set-bad-yaml", ("--set", "alpha=[1"), "not valid YAML"),
    ("flag-and-set-clash", ("--n-envs", "2", "--set", "n_envs=3"), "n_envs given twice: --n-envs 2 and --set n_envs=3"),
    ("seeds-past-int32", ("--seed", "2147483647", "--seeds", "2"), "which must lie in [0, 2147483647]"),
    # each run fits (a few GB); its 128 rows at once do not
    ("group-too-big-for-memory",
     ("--grid", "alpha=0.1,0.2", "--seeds", "64", "--n-envs", "200000", "--nepisodes", "10"),
     "sweep group 1 (128 rows)"),
    ("second-group-bad", ("--grid", "number_splits=4,100000"), "number_splits"),
    # silently dropped or overridden: a key given twice, swept and fixed at once, an empty value
    ("grid-key-twice", ("--grid", "alpha=0.1", "--grid", "alpha=0.2"), "--grid alpha: given twice"),
    ("grid-and-nsteps", ("--grid", "nsteps=10,30", "--nsteps", "20"),
     "nsteps: swept by --grid/--range and fixed by --nsteps 20"),
    ("grid-and-n-envs", ("--grid", "n_envs=2,4", "--n-envs", "8"), "fixed by --n-envs 8"),
    ("grid-and-set", ("--grid", "alpha=0.1,0.2", "--set", "alpha=0.3"), "alpha: swept by --grid/--range and fixed by "
     "--set alpha=0.3"),
    ("grid-and-prefixed-set", ("--grid", "alpha=0.1,0.2", "--set", "agent.alpha=0.3"), "fixed by --set agent.alpha"),
    ("range-and-set", ("--random", "2", "--range", "alpha=0.1:0.9", "--set", "alpha=0.3"), "alpha: swept by"),
    ("range-key-twice", ("--random", "2", "--range", "alpha=0.1:0.5", "--range", "alpha=0.2:0.6"),
     "--range alpha: given twice"),
    ("grid-empty-value", ("--grid", "alpha=0.1,,0.3"), "--grid 'alpha=0.1,,0.3': value 2 of 3 is empty"),
    ("grid-value-twice", ("--grid", "alpha=0.1,0.3,0.10"), "--grid 'alpha=0.1,0.3,0.10': value 0.1 is given twice"),
    ("grid-list-value-twice", ("--grid", "rand_cart_mass=[1,1],[1,1]"), "value [1, 1] is given twice"),
    ("grid-trailing-comma", ("--grid", "alpha=0.1,"), "value 2 of 2 is empty"),
    ("grid-only-commas", ("--grid", "alpha=,"), "value 1 of 2 is empty"),
    ("set-float32-zero", ("--set", "alpha=1e-320"), "alpha=1e-320: is 0 in float32"),
    ("grid-float32-zero", ("--grid", "alpha=0.1,1e-320"), "is 0 in float32"),
    # memory: rows planned, and the evaluation, refused before anything is built or compiled
    ("random-huge", ("--random", "1000000000", "--range", "alpha=0.1:0.9"),
     "1,000,000,000 configurations x 4 seeds = 4,000,000,000 rows: planning them needs about"),
    ("seeds-huge", ("--seeds", "2000000000"), "1 configurations x 2,000,000,000 seeds"),
    ("grid-product-huge", ("--grid", "alpha=" + ",".join(str(0.001 * (i + 1)) for i in range(1000)),
                           "--grid", "gamma=" + ",".join(str(0.0009 * (i + 1)) for i in range(1000)),
                           "--seeds", "1000"), "= 1,000,000,000 rows"),
    ("eval-episodes-huge", ("--eval-episodes", "1000000000"), "eval_episodes=1000000000: the greedy evaluation of"),
]]

SWEEP += [
    Case("sweep-out-symlink-loop", "sweep", (), "--out {tmp}/out: a symlink loop", out_link("out")),
    Case("sweep-num-processes-not-int", "sweep", (), "JAXROBO_NUM_PROCESSES='abc': expected an integer >= 1",
         setenv(JAXROBO_NUM_PROCESSES="abc", JAXROBO_COORDINATOR="localhost:1234", JAXROBO_PROCESS_ID="0")),
    Case("sweep-process-id-out-of-range", "sweep", (), "JAXROBO_PROCESS_ID=5: must be in 0..1",
         setenv(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="localhost:1234", JAXROBO_PROCESS_ID="5")),
    Case("sweep-coordinator-unresolvable", "sweep", (), "JAXROBO_COORDINATOR='nonexistent.invalid:1234': the host "
         "'nonexistent.invalid' does not resolve",
         setenv(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="nonexistent.invalid:1234", JAXROBO_PROCESS_ID="0")),
    Case("sweep-coordinator-no-port", "sweep", (), "JAXROBO_COORDINATOR='myhost': expected host:port",
         setenv(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="myhost", JAXROBO_PROCESS_ID="0")),
    Case("sweep-resume-module-env", "sweep", ("--resume", "{tmp}/sw"),
         f"names the Python module '{EVIL}', which a file read back never imports",
         interrupted_sweep(f"{EVIL}:Foo-v0"), out=False),
    Case("train-resume-of-a-sweep", "train", ("--resume", "{tmp}/sw"),
         "--resume {tmp}/sw: is an interrupted sweep, not a train run; go on with jaxrobo sweep --resume {tmp}/sw",
         interrupted_sweep(CP), out=False),
    # hand-edited saved flags: refused naming the flag, where they failed deep in the sweep with a traceback
    Case("sweep-resume-saved-seeds-str", "sweep", ("--resume", "{tmp}/sw"),
         "sweep_state.json: saved flag --seeds='4': expected an integer", interrupted_sweep(CP, seeds="4"), out=False),
    Case("sweep-resume-saved-metric-unknown", "sweep", ("--resume", "{tmp}/sw"),
         "sweep_state.json: saved flag --metric='best': expected one of final_return,",
         interrupted_sweep(CP, metric="best"), out=False),
    Case("sweep-resume-saved-no-plots-str", "sweep", ("--resume", "{tmp}/sw"),
         "saved flag --no-plots='yes': expected true or false", interrupted_sweep(CP, no_plots="yes"), out=False),
    Case("sweep-resume-saved-grid-str", "sweep", ("--resume", "{tmp}/sw"),
         "saved flag --grid='alpha=0.1': expected a list of strings", interrupted_sweep(CP, grid="alpha=0.1"),
         out=False),
]


def P(id: str, fragment: str, *argv: str, setup=None) -> Case:  # noqa: N802 - a table row
    return Case(f"plot-{id}", "plot", argv, fragment, setup)


def csv_run(filename: str, text: str | bytes, name: str = "r"):
    return lambda tmp, _mp: write_csv_run(tmp, name, filename, text)


PLOT = [
    P("missing-dir", "run directory '{tmp}/nope' does not exist", "{tmp}/nope"),
    P("no-csv", "no episode_stats.csv or episodes.csv", "{tmp}/r", setup=lambda tmp, _mp: os.makedirs(f"{tmp}/r")),
    P("stats-missing-columns", "missing column(s) return_p10, return_p90", "{tmp}/r",
      setup=csv_run("episode_stats.csv", "episode,return_mean,length_mean,length_p10,length_p90\n0,1,2,3,4\n")),
    P("stats-truncated", "episode_stats.csv line 3: expected 12 values", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER + STATS_ROW + "1,1,0,1\n")),
    P("stats-not-a-number", "line 2: column return_mean='abc' is not a number", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER + STATS_ROW.replace("0,1,", "0,abc,", 1))),
    P("stats-header-only", "episode_stats.csv has no rows", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER)),
    P("stats-binary", "not a text CSV file", "{tmp}/r", setup=csv_run("episode_stats.csv", b"\xff\xfe\x00\x81bad")),
    P("episodes-missing-column", "missing column(s) epsilon", "{tmp}/r",
      setup=csv_run("episodes.csv", "env,episode,return,length,terminated\n0,0,1,2,0\n")),
    P("episodes-negative-env", "episodes.csv line 2: column env=-1: expected a whole number in 0..2147483647",
      "{tmp}/r", setup=csv_run("episodes.csv", "env,episode,return,length,terminated,epsilon\n"
                                               "-1,0,1,2,0,0.1\n")),
    # a value that is finite and whole but no index (its cast to int is garbage), and a pair whose product
    # overflows int64 (the size check would pass a wrapped number)
    P("episodes-env-1e300", "episodes.csv line 3: column env=1e+300: expected a whole number in 0..2147483647",
      "{tmp}/r", setup=csv_run("episodes.csv", "env,episode,return,length,terminated,epsilon\n0,0,1,2,0,0.1\n"
                                               "1e300,0,1,2,0,0.1\n")),
    P("episodes-index-overflow", "episodes.csv line 2: column env=3037000500: expected a whole number", "{tmp}/r",
      setup=csv_run("episodes.csv", "env,episode,return,length,terminated,epsilon\n"
                                    "3037000500,3037000500,1,2,0,0.1\n")),
    P("episodes-fractional-episode", "line 2: column episode=0.5: expected a whole number", "{tmp}/r",
      setup=csv_run("episodes.csv", "env,episode,return,length,terminated,epsilon\n0,0.5,1,2,0,0.1\n")),
    P("episodes-duplicate-column", "episodes.csv: column(s) 'return' named twice in the header", "{tmp}/r",
      setup=csv_run("episodes.csv", "env,episode,return,length,terminated,epsilon,return\n0,0,1,2,0,0.1,3\n"
                                    "0,1,1,2,0,0.1,3\n")),
    P("stats-duplicate-column", "episode_stats.csv: column(s) 'return_mean' named twice", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER.replace("\n", ",return_mean\n") + STATS_ROW.replace("\n", ",1\n")
                    + STATS_ROW.replace("0,", "1,", 1).replace("\n", ",1\n"))),
    P("stats-episode-nan", "episode_stats.csv line 2: column episode=nan: expected a whole number in 0..2147483647",
      "{tmp}/r", setup=csv_run("episode_stats.csv", STATS_HEADER + STATS_ROW.replace("0,", "nan,", 1))),
    P("stats-episode-fraction", "episode_stats.csv line 3: column episode=1.5: expected a whole number", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER + STATS_ROW + STATS_ROW.replace("0,", "1.5,", 1))),
    P("stats-episode-negative", "episode_stats.csv line 2: column episode=-3: expected a whole number", "{tmp}/r",
      setup=csv_run("episode_stats.csv", STATS_HEADER + STATS_ROW.replace("0,", "-3,", 1))),
    P("x-not-a-choice", "jaxrobo plot: argument --x: invalid choice: 'time' (choose from", "{tmp}/r", "--x", "time"),
    P("window-not-int", "jaxrobo plot: argument --window: invalid int value: '2.5'", "{tmp}/r", "--window", "2.5"),
    P("second-run-broken", "missing column(s)", "{tmp}/r", "{tmp}/s",
      setup=lambda tmp, mp: (write_csv_run(tmp, "r", "episode_stats.csv", STATS_HEADER + STATS_ROW),
                             write_csv_run(tmp, "s", "episode_stats.csv", "episode\n0\n"))),
]


def S(id: str, fragment: str, *argv: str, setup=None) -> Case:  # noqa: N802 - a table row
    return Case(f"show-{id}", "show", argv + ("--out", "{tmp}/out/flights.png"), fragment, setup)


SHOW = [
    S("episodes-not-int", "jaxrobo show: argument --episodes: invalid int value: 'many'", "{tmp}/r", "--episodes",
      "many"),
    S("missing-dir", "run directory '{tmp}/nope' does not exist", "{tmp}/nope"),
    S("no-config", "no config.yaml; is it a jaxrobo run directory?", "{tmp}/run", setup=run_dir(config=None)),
    S("config-malformed", "config.yaml: not valid YAML", "{tmp}/run", setup=run_dir(config_text="env_id: [1\n")),
    S("config-pickle-tag", "could not determine a constructor", "{tmp}/run",
      setup=run_dir(config_text="env_id: !!python/object/apply:os.system ['ls']\n")),
    S("config-not-mapping", "expected a mapping of key: value at the top level", "{tmp}/run",
      setup=run_dir(config_text="- 1\n")),
    S("config-duplicate-key", "duplicate key 'env_id'", "{tmp}/run",
      setup=run_dir(config_text=f"env_id: {GOTO}\nenv_id: {CP}\n")),
    S("config-no-env-id", "env_id is missing", "{tmp}/run", setup=run_dir(config_text="preset: default\n")),
    S("config-section-not-mapping", "train must be a mapping of key: value", "{tmp}/run",
      setup=run_dir(config_text=f"env_id: {GOTO}\ntrain: 5\n")),
    S("config-bad-value", "alpha=5.0: expected a number > 0.0", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, config={**goto_config(), "agent_params": {"alpha": 5}})),
    S("config-unknown-env", "environment id: unknown key 'Nope-v0'", "{tmp}/run",
      setup=run_dir(config_text="env_id: Nope-v0\n")),
    S("cartpole-run-no-tables", "no qtables.npz", "{tmp}/run", setup=run_dir(config_text=f"env_id: {CP}\n", q=None)),
    S("no-tables", "no qtables.npz", "{tmp}/run", setup=run_dir(q=None)),
    S("truncated-npz", "cannot be read as plain arrays", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, npz=ok_npz_bytes(tmp)[:100])),
    S("pickled-npz", "cannot be read as plain arrays", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, npz=pickled_npz_bytes(tmp))),
    S("not-an-npz", "cannot be read as plain arrays", "{tmp}/run", setup=run_dir(npz=b"hello, not a zip file")),
    S("npz-without-q", "no array 'q' (found tables)", "{tmp}/run", setup=run_dir(q={"tables": np.zeros(3)})),
    S("q-wrong-ndim", "q must be a float array [n_envs, n_tables, n_states, n_actions], got float32 of shape (3, 4)",
      "{tmp}/run", setup=run_dir(q=np.zeros((3, 4), np.float32))),
    S("q-wrong-shape", "q has shape (1, 1, 10, 5), but the run's config.yaml gives (1, 1, 1296, 5)",
      "{tmp}/run", setup=run_dir(q=np.zeros((1, 1, 10, 5), np.float32))),
    S("q-two-tables-for-qlearn", "q has shape (1, 2, 1296, 5), but the run's config.yaml gives (1, 1, 1296, 5)",
      "{tmp}/run", setup=run_dir(q=np.zeros((1, 2, 1296, 5), np.float32))),
    S("q-no-tables", "holds no table", "{tmp}/run", setup=run_dir(q=np.zeros((0, 1, 1296, 5), np.float32))),
    S("discretiser-strings", "low is <U3 of shape (7,), expected float32 of shape (7,)", "{tmp}/run",
      setup=tampered(low=np.array(["abc"] * 7))),
    S("q-all-nan", "table 0 has 6480 non-finite values of 6480", "{tmp}/run",
      setup=run_dir(q=np.full((1, 1, 1296, 5), np.nan, np.float32))),
    S("table-out-of-range", "--table 5: must be in 0..0 (the run has 1 tables)", "{tmp}/run", "--table", "5",
      setup=run_dir()),
    S("table-negative", "--table -1: must be an integer >= 0", "{tmp}/run", "--table", "-1", setup=run_dir()),
    S("episodes-zero", "--episodes 0: must be an integer >= 1 and <= 100", "{tmp}/run", "--episodes", "0",
      setup=run_dir()),
    S("episodes-huge", "--episodes 100000: must be an integer >= 1 and <= 100", "{tmp}/run", "--episodes", "100000",
      setup=run_dir()),
    S("seed-negative", "--seed -1: must be an integer >= 0", "{tmp}/run", "--seed", "-1", setup=run_dir()),
    S("run-and-env", "give a RUN_DIR or --env ID, not both", "{tmp}/run", "--env", GOTO, setup=run_dir()),
    S("neither", "give a RUN_DIR (greedy flights of a trained run) or --env ID"),
    S("env-cartpole-episodes-zero", "--episodes 0: must be an integer >= 1", "--env", CP, "--episodes", "0"),
    S("env-unknown", "environment id: unknown key 'Nope-v0'", "--env", "Nope-v0"),
    S("env-bad-preset", "preset='nope': allowed values are default, seed", "--env", GOTO, "--preset", "nope"),
    S("config-key-of-another-env", "{tmp}/run/config.yaml: unknown key '", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, config=cp_config(env_id="ArmReach-v0"))),
    # flags that would be silently ignored
    S("env-with-table", "--table 1: --env flies a random policy, which has no tables", "--env", GOTO, "--table", "1"),
    S("env-with-policy", "--policy best: --env flies a random policy", "--env", GOTO, "--policy", "best"),
    S("run-with-preset", "--preset seed: a run directory flies with its own config.yaml", "{tmp}/run", "--preset",
      "seed", setup=run_dir()),
    S("tabular-run-with-policy", "--policy best: {tmp}/run is a tabular run", "{tmp}/run", "--policy", "best",
      setup=run_dir()),
    Case("show-video-and-out", "show", ("{tmp}/run", "--video", "{tmp}/v.gif", "--out", "{tmp}/f.png"),
         "--out '{tmp}/f.png' with --video: --video writes the episode instead of the figure", run_dir()),
    Case("show-out-not-image", "show", ("{tmp}/run", "--out", "{tmp}/flights.txt"),
         "--out '{tmp}/flights.txt': expected an image file", run_dir()),
    # hostile config.yaml and qtables.npz
    S("config-alias-bomb", "YAML aliases (*name) are not accepted", "{tmp}/run", setup=run_dir(config_text=ALIAS_BOMB)),
    S("config-deep-nesting", "nested deeper than 32 levels", "{tmp}/run", setup=run_dir(config_text=DEEP)),
    S("config-huge", "more than a config holds", "{tmp}/run", setup=run_dir(config_text=HUGE)),
    S("config-nul", "holds NUL bytes", "{tmp}/run", setup=run_dir(config_text="env_id: a\0b\n")),
    S("config-module-env-id", f"names the Python module '{EVIL}'", "{tmp}/run",
      setup=lambda tmp, mp: (write_run(tmp, config_text=f"env_id: {EVIL}:Foo-v0\n"), evil_module(tmp, mp))),
    S("npz-header-2-to-the-40-rows", "array 'q' claims shape (1099511627776, 1, 1, 1296, 5)", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, npz=forged_npz(tmp))),
    S("npz-header-negative-rows", "has no valid .npy header", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, npz=forged_npz(tmp, "-5, "))),
    S("npz-bit-flipped", "cannot be read as plain arrays", "{tmp}/run",
      setup=lambda tmp, mp: write_run(tmp, npz=flipped_npz(tmp))),
    S("q-int-dtype", "q must be a float array [n_envs, n_tables, n_states, n_actions], got int32",
      "{tmp}/run", setup=run_dir(q=np.zeros((1, 1, 1296, 5), np.int32))),
    S("q-inf-table", "table 0 has 1 non-finite values of 6480", "{tmp}/run",
      setup=run_dir(q=np.where(np.arange(6480).reshape(1, 1, 1296, 5) == 7, np.inf, 0).astype(np.float32))),
]


def disc_rows(row: Callable[..., Case], *argv: str) -> list[Case]:
    """The discretiser saved beside ``q`` in ``qtables.npz`` against the one the run's config builds
    (:func:`jaxrobo.io.results.check_saved_discretiser`), as ``row`` (show, eval, export) refuses it."""
    return [row(id, fragment, "{tmp}/run", *argv, setup=setup) for id, fragment, setup in [
        # members: each of the config's discretiser, no other
        ("disc-missing-low", "run/qtables.npz: no array 'low' of the discretiser (found width, bins); expected low, "
         "width, bins: the uniform discretiser the run's config.yaml builds", tampered(low=None)),
        ("disc-only-q", "no array 'low' of the discretiser (found none)", tampered(low=None, width=None, bins=None)),
        ("disc-missing-edges", "run/qtables.npz: no array 'edges_7' of the discretiser (found low, width, bins, "
         "edges_0", tampered(GOTO2, edges_7=None)),
        ("disc-edges-of-uniform", "run/qtables.npz: array 'edges_0' is no part of the uniform discretiser the run's "
         "config.yaml builds (7 dimensions: low, width, bins)", tampered(edges_0=np.zeros(1))),
        ("disc-edges-beyond", "array 'edges_8' is no part of the edges discretiser the run's config.yaml builds "
         "(8 dimensions: low, width, bins, edges_0,", tampered(GOTO2, edges_8=np.zeros(1))),
        # shapes and dtypes
        ("disc-low-short", "run/qtables.npz: low is float32 of shape (6,), expected float32 of shape (7,) (one per "
         "observation dimension", tampered(low=lambda x: x[:6])),
        ("disc-width-float64", "width is float64 of shape (7,), expected float32 of shape (7,)",
         tampered(width=lambda x: x.astype(np.float64))),
        ("disc-bins-2d", "bins is int64 of shape (1, 7), expected integers of shape (7,)",
         tampered(bins=lambda x: x[None])),
        ("disc-bins-bool", "bins is bool of shape (7,), expected integers of shape (7,)",
         tampered(bins=lambda x: x > 0)),
        ("disc-edges-short", "edges_1 is float64 of shape (7,), expected float64 of shape (8,) (that dimension's "
         "interior edges", tampered(GOTO2, edges_1=lambda x: x[:7])),
        # values: finite, whole bins >= 1 whose product is q's states, each the config's
        ("disc-low-nan", "run/qtables.npz: low=[nan, -3.1415927, -0.75, 0.0, ", tampered(low=nudged(0, np.nan))),
        ("disc-width-inf", "holds 1 non-finite values (NaN or inf); expected finite numbers",
         tampered(width=nudged(2, np.inf))),
        ("disc-edges-inf", "edges_3=[1.0, inf] holds 1 non-finite values", tampered(GOTO2, edges_3=nudged(1, np.inf))),
        ("disc-bins-fractional", "bins=[2.5, 9.0, 3.0,", tampered(bins=lambda x: x + np.eye(7)[0] / 2)),
        ("disc-bins-float", "(float64): expected whole numbers >= 1 as integers, one per observation dimension",
         tampered(bins=lambda x: x.astype(np.float64))),
        ("disc-bins-zero", "run/qtables.npz: bins=[0, 9, 3,", tampered(bins=nudged(0, -2))),
        ("disc-bins-negative", "expected whole numbers >= 1, one per observation dimension",  # the product kept
         tampered(bins=lambda x: x * np.array([-1, -1, 1, 1, 1, 1, 1]))),
        ("disc-bins-product", "run/qtables.npz: q of shape (1, 1, 1296, 5) has 1296 states, but its bins=[3, 9, 3,",
         tampered(bins=nudged(0, 1))),
        ("disc-bins-differ", "the discretiser's bins[0]=1, but the run's config.yaml builds bins[0]=2 (uniform "
         "discretiser); the files are not of one run", tampered(bins=lambda x: x * np.array([1, 1, 2, 1, 1, 1, 1]) //
                                                                 np.array([2, 1, 1, 1, 1, 1, 1]))),
        ("disc-low-differs", "the discretiser's low[1]=-2.6415927, but the run's config.yaml builds low[1]=-3.1415927",
         tampered(low=nudged(1, 0.5))),
        ("disc-width-differs", "the discretiser's width[6]=", tampered(width=nudged(6, 1e-6))),
        ("disc-edges-differ", "the discretiser's edges_1[3]=", tampered(GOTO2, edges_1=nudged(3, 1e-9))),
        ("disc-edges-width-differs", "builds width[0]=1.0 (edges discretiser)", tampered(GOTO2, width=nudged(0, 1))),
    ]]


def E(id: str, fragment: str, *argv: str, setup=None) -> Case:  # noqa: N802 - a table row
    return Case(f"eval-{id}", "eval", argv + ("--out", "{tmp}/out"), fragment, setup)


def X(id: str, fragment: str, *argv: str, setup=None) -> Case:  # noqa: N802 - a table row
    return Case(f"export-{id}", "export", argv + ("--out", "{tmp}/out"), fragment, setup)


SHOW += disc_rows(S)
EVAL = disc_rows(E, "--shift", "mass=1")
EXPORT = disc_rows(X)

def _mkstemp_erofs(tmp: str, monkeypatch: Any) -> None:
    from jaxrobo.speed import cache

    def erofs(*_a, **_kw):
        raise OSError(30, "Read-only file system")

    monkeypatch.setenv("JAXROBO_CACHE_DIR", os.path.join(tmp, "cache"))
    os.makedirs(os.path.join(tmp, "cache"))
    monkeypatch.setattr(cache.tempfile, "mkstemp", erofs)


def _cache_file(sub: str = "") -> Callable[[str, Any], None]:
    def setup(tmp: str, monkeypatch: Any) -> None:
        with open(os.path.join(tmp, "file"), "w") as f:
            f.write("x")
        monkeypatch.setenv("JAXROBO_CACHE_DIR", os.path.join(tmp, "file", sub) if sub else os.path.join(tmp, "file"))
    return setup


LIST = [
    # an unusable compilation cache is a warning and the cache off, never an error
    Case("list-cache-dir-is-a-file", "list", (), "warning: JAXROBO_CACHE_DIR='{tmp}/file': cannot use it",
         _cache_file(), code=0),
    Case("list-cache-dir-under-a-file", "list", (), "warning: JAXROBO_CACHE_DIR='{tmp}/file/sub': cannot use it",
         _cache_file("sub"), code=0),
    Case("list-cache-dir-read-only", "list", (), "(Read-only file system); the compilation cache is off",
         _mkstemp_erofs, code=0),
    Case("list-broken-agent-yaml", "list", (), f"note: {CP}: ", agent_yaml("default: [1, 2\n"), code=0),
    Case("list-duplicate-key-agent-yaml", "list", (), "duplicate key 'alpha'",
         agent_yaml("default:\n  alpha: 0.1\n  alpha: 0.2\n"), code=0),
]


def _make(*a, **kw):
    import jaxrobo

    return jaxrobo.make(*a, **kw)


def _resolve(*a, **kw):
    from jaxrobo.training.run import resolve

    return resolve(*a, **kw)


def _disc(*a, **kw):
    from jaxrobo.tabular.discretise import make_discretiser

    return make_discretiser(*a, **kw)


def _gym_make(*a, **kw):
    import gymnasium as gym

    import jaxrobo  # noqa: F401  (registers the jaxrobo/ ids)

    return gym.make(*a, **kw)


def _yaml_file(text: str) -> dict[str, Any]:
    """A call of load_yaml on a file holding ``text`` (written by the case's setup, before the snapshot)."""
    def setup(tmp: str, _mp: Any) -> None:
        with open(os.path.join(tmp, "in.yaml"), "w") as f:
            f.write(text)
    return {"call": lambda tmp: load_yaml(os.path.join(tmp, "in.yaml")), "setup": setup}


def A(id: str, fragment: str, call: Any) -> Case:  # noqa: N802 - a table row
    if isinstance(call, dict):
        return Case(f"api-{id}", "api", call["call"], fragment, call["setup"])
    return Case(f"api-{id}", "api", call, fragment)


CHECK = [
    Case("check-long-not-int", "check", (CP, "--long", "1.5"), "jaxrobo check: argument --long: invalid int value"),
    Case("check-no-id", "check", (), "jaxrobo check: the following arguments are required: ID"),
    Case("check-seed-int64-overflow", "check", (CP, "--seed", "99999999999999999999"),
         "seed=99999999999999999999: expected an integer >= 0 and <= 2147483647"),
    Case("check-seed-negative", "check", (CP, "--seed", "-1"), "seed=-1: expected an integer >= 0"),
    Case("check-unknown-id", "check", ("Nope-v0",), "environment id: unknown key 'Nope-v0'"),
]


def _env_call(fn: Callable[[Any], Any]) -> Callable[[str], Any]:
    """A call on a made cart-pole env (analytic: no model to compile for a refusal at trace time)."""
    def call(_tmp: str) -> Any:
        import jax

        import jaxrobo

        env = jaxrobo.make(CP, backend="analytic")
        return fn((env, env.reset(jax.random.key(0)), jax))
    return call


#: The functions the fixture stubs, as they were (:func:`_train` calls the real train(), whose checks must refuse
#: before the stubbed Trainer.init).
_REAL: dict[str, Callable[..., Any]] = {}


def _train(config: dict | None = None, agent: dict | None = None, env: dict | None = None, env_id: str = CP,
           raw: dict | None = None, **kw: Any) -> Callable[[str], Any]:
    """``train(env, config, agent_params, env_params, **kw)`` as a Python caller calls it: a small resolved cart-pole
    run with the fields of ``config`` / ``agent`` / ``env`` replaced, the env ``env_id``'s, and the arguments of
    ``raw`` given as they are."""
    def call(_tmp: str) -> Any:
        import jaxrobo
        from jaxrobo.training.run import resolve

        spec = resolve(CP, overrides={"env.backend": "analytic", "n_envs": 4, "nepisodes": 2})
        made = spec.env if env_id == CP else jaxrobo.make(env_id)
        args = {"config": spec.config.replace(**(config or {})),
                "agent_params": spec.agent_params.replace(**(agent or {})),
                "env_params": made.default_params.replace(**env) if env else None, **(raw or {})}
        return _REAL["train"](made, **args, **kw)
    return call


def _deep_train(**config: Any) -> dict[str, Any]:
    """``jaxrobo.deep.training.train(spec)`` of the tiny PPO preset's spec with fields of its config replaced, as a
    Python caller edits one; Brax's trainer stubbed to fail (the fixture stubs only the package's name)."""
    def setup(_tmp: str, mp: Any) -> None:
        from jaxrobo.deep import training

        def reached(*_a: Any, **_kw: Any) -> None:
            raise AssertionError("deep.train's epoch plan was reached: the spec was not refused")
        mp.setattr(training, "epoch_plan", reached)

    def call(_tmp: str) -> Any:
        from jaxrobo import deep
        from jaxrobo.deep import training

        spec = deep.resolve("CartPoleContinuous-v0", "ppo", "tiny")
        return training.train(dataclasses.replace(spec, config=dataclasses.replace(spec.config, **config)))
    return {"call": call, "setup": setup}


def _distributed(**values: str) -> dict[str, Any]:
    def call(_tmp: str) -> Any:
        from jaxrobo.speed import sharding

        return sharding.initialize_distributed()
    return {"call": call, "setup": setenv(**values)}


API = [
    A("make-int-id", "jaxrobo.make(id=123): expected an environment id string", raises(lambda: _make(123))),
    A("make-none-id", "jaxrobo.make(id=None): expected an environment id string", raises(lambda: _make(None))),
    A("make-list-id", "jaxrobo.make(id=['CartPoleStayUp-v0'])", raises(lambda: _make([CP]))),
    A("reset-int-key", "reset(key): expected one PRNG key such as jax.random.key(seed), got int 0",
      _env_call(lambda e: e[0].reset(0))),
    A("reset-float-key", "reset(key): expected one PRNG key", _env_call(lambda e: e[0].reset(1.5))),
    A("reset-key-batch", "got an array of key<fry> with shape (3,)",
      _env_call(lambda e: e[0].reset(e[2].random.split(e[2].random.key(0), 3)))),
    A("reset-key-batch-under-jit", "(vmap over a batch of keys)",
      _env_call(lambda e: e[2].jit(e[0].reset)(e[2].random.split(e[2].random.key(0), 3)))),
    A("step-action-vector", "step(state, action): action has shape (2,); one env's action is Discrete(",
      _env_call(lambda e: e[0].step(e[1], e[2].numpy.array([1, 0])))),
    A("step-action-vector-under-jit", "action has shape (1,)",
      _env_call(lambda e: e[2].jit(e[0].step)(e[1], e[2].numpy.array([1])))),
    A("num-processes-not-int", "JAXROBO_NUM_PROCESSES='abc': expected an integer >= 1",
      _distributed(JAXROBO_NUM_PROCESSES="abc", JAXROBO_COORDINATOR="localhost:1", JAXROBO_PROCESS_ID="0")),
    A("num-processes-zero", "JAXROBO_NUM_PROCESSES=0: expected an integer >= 1",
      _distributed(JAXROBO_NUM_PROCESSES="0", JAXROBO_COORDINATOR="localhost:1", JAXROBO_PROCESS_ID="0")),
    A("process-id-negative", "JAXROBO_PROCESS_ID=-1: expected an integer >= 0",
      _distributed(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="localhost:1", JAXROBO_PROCESS_ID="-1")),
    A("coordinator-unresolvable", "does not resolve",
      _distributed(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="nope.invalid:1", JAXROBO_PROCESS_ID="0")),
    A("coordinator-bad-port", "JAXROBO_COORDINATOR='localhost:99999': expected host:port (port 1..65535)",
      _distributed(JAXROBO_NUM_PROCESSES="2", JAXROBO_COORDINATOR="localhost:99999", JAXROBO_PROCESS_ID="0")),
    A("train-n-envs-zero", "train(config): n_envs=0: expected an integer >= 1", _train({"n_envs": 0})),
    A("train-n-envs-not-int", "train(config): n_envs=2.5: expected an integer", _train({"n_envs": 2.5})),
    A("train-nepisodes-zero", "train(config): nepisodes=0: expected an integer >= 1", _train({"nepisodes": 0})),
    A("train-agent-unknown", "train(config): agent='nope': allowed values are", _train({"agent": "nope"})),
    A("train-snapshots-without-shared-table", "snapshots=2 needs shared_table=true", _train({"snapshots": 2})),
    A("train-bins-wrong-length", "train(config): bins=[2, 2]: expected 4 bin counts", _train({"bins": (2, 2)})),
    A("train-alpha-nan", "train(agent_params): alpha=nan: must be finite", _train(agent={"alpha": float("nan")})),
    A("train-alpha-range", "train(agent_params): alpha=7.0: expected a number > 0.0 and <= 1.0",
      _train(agent={"alpha": 7.0})),
    A("train-alpha-array-nan", "train(agent_params): alpha=nan: expected a number > 0.0",
      _train(agent={"alpha": np.float32("nan")})),
    A("train-env-param-range", "train(env_params): max_episode_steps=0: expected an integer >= 1",
      _train(env={"max_episode_steps": 0})),
    A("train-env-params-dict", "train(env_params=...): expected envs.cartpole.stay_up.Params, got dict",
      _train(raw={"env_params": {"max_episode_steps": 5}})),
    A("train-config-dict", "train(config=...): expected a jaxrobo.training.trainer.TrainConfig",
      _train(raw={"config": {"n_envs": 4}})),
    A("train-start-chunk-negative", "train(start_chunk=-1): expected an integer >= 0", _train(start_chunk=-1)),
    A("train-checkpoint-every-negative", "train(checkpoint_every=-5): expected an integer >= 0",
      _train(checkpoint_every=-5)),
    A("train-checkpoint-seconds-nan", "train(checkpoint_seconds=nan): expected a number of seconds >= 0",
      _train(checkpoint_seconds=float("nan"))),
    A("train-callbacks-not-iterable", "callbacks: 5 is neither", _train(callbacks=5)),
    A("train-tabular-on-box-id", "CartPoleContinuous-v0 has continuous (Box) actions",
      _train(env_id="CartPoleContinuous-v0")),
    A("deep-train-num-envs-zero", "deep.train(spec): num_envs=0: expected an integer >= 1", _deep_train(num_envs=0)),
    A("deep-train-learning-rate-nan", "deep.train(spec): learning_rate=nan: must be finite",
      _deep_train(learning_rate=float("nan"))),
    A("deep-train-batch-not-multiple", "deep.train(spec): batch_size x num_minibatches = 3 x 4 = 12 must be a "
      "multiple of num_envs=8", _deep_train(batch_size=3)),
    A("resolve-float32-zero", "alpha=1e-320: is 0 in float32",
      raises(lambda: _resolve(CP, overrides={"alpha": 1e-320}))),
    A("make-float32-inf", "is inf in float32", raises(lambda: _make(CP, pos_step=1e39))),
    A("yaml-alias", "YAML aliases (*name) are not accepted", _yaml_file("a: &x 1\nb: *x\n")),
    A("yaml-merge-key-alias", "YAML aliases", _yaml_file("base: &b {alpha: 1}\nd:\n  <<: *b\n")),
    A("yaml-alias-bomb", "YAML aliases", _yaml_file(ALIAS_BOMB)),
    A("yaml-deep-nesting", "nested deeper than 32 levels", _yaml_file(DEEP)),
    A("yaml-deep-mappings", "nested deeper than 32 levels", _yaml_file("a: " + "{b: " * 40 + "1" + "}" * 40 + "\n")),
    A("yaml-huge", "more than a config holds", _yaml_file(HUGE)),
    A("yaml-many-nodes", "more than 100000 values", _yaml_file("a: [" + "1, " * 150_000 + "1]\n")),
    A("out-name-too-long", "a name too long for the file system", lambda tmp: _check_out(os.path.join(tmp, "x" * 300))),
    A("out-name-too-long-for-staging", "bytes; at most", lambda tmp: _check_out(os.path.join(tmp, "x" * 250))),
    A("out-under-proc", "--out /proc/nope/run: cannot write in /proc", lambda tmp: _check_out("/proc/nope/run")),
    A("out-nul", "a path cannot hold a NUL character", lambda tmp: _check_out(os.path.join(tmp, "a\0b"))),
    A("make-unknown-key", "unknown key 'pos_stepp' (did you mean pos_step", raises(lambda: _make(CP, pos_stepp=1))),
    A("make-unknown-id", "environment id: unknown key 'Nope'", raises(lambda: _make("Nope"))),
    A("make-int32", "max_episode_steps=1099511627776: expected an integer >= 1 and <= 2147483647",
      raises(lambda: _make(CP, max_episode_steps=2**40))),
    A("make-choice", "n_actions=3: allowed values are 2, 4", raises(lambda: _make(CP, n_actions=3))),
    A("make-wrong-type", "pos_step='fast': expected a number", raises(lambda: _make(CP, pos_step="fast"))),
    A("gym-make-unknown-key", "unknown key 'pos_stepp'", raises(lambda: _gym_make(f"jaxrobo/{CP}", pos_stepp=1))),
    A("resolve-string-number", "alpha='1e-3': expected a number",
      raises(lambda: _resolve(CP, overrides={"alpha": "1e-3"}))),
    A("resolve-overrides-not-mapping", "overrides: expected a mapping of key: value, got list",
      raises(lambda: _resolve(CP, overrides=[("alpha", 0.1)]))),
    A("resolve-non-string-key", "--set: unknown key '1'", raises(lambda: _resolve(CP, overrides={1: 2}))),
    A("resolve-preset-none", "preset=None: allowed values are default, seed", raises(lambda: _resolve(CP, None))),
    A("resolve-memory", "n_envs=1000000000: the batch needs at least",
      raises(lambda: _resolve(CP, overrides={"n_envs": 10**9}))),
    A("resolve-double-q-seed-compat", "agent='double_q' with seed_compat=true",
      raises(lambda: _resolve(CP, overrides={"agent": "double_q", "seed_compat": True}))),
    A("resolve-ignored-number-splits", "number_splits=20 would be ignored",
      raises(lambda: _resolve(CP, overrides={"agent.number_splits": 20}))),
    A("resolve-bins-tuple-wrong-length", "bins=[2, 2]: expected 4 bin counts",
      raises(lambda: _resolve(CP, overrides={"bins": (2, 2)}))),
    A("disc-unequal-bounds", "high=[1]: expected 2 values, one per observation dimension, got 1 (low and high must "
      "be equal-length lists)", raises(lambda: _disc([0, 0], [1], number_splits=3))),
    A("disc-splits-length", "number_splits=[2, 3]: expected 1 bin counts",
      raises(lambda: _disc([0], [1], number_splits=[2, 3]))),
    A("disc-splits-string", "number_splits='3': expected a positive integer",
      raises(lambda: _disc([0], [1], number_splits="3"))),
    A("disc-splits-zero", "number_splits=0: expected an integer >= 1",
      raises(lambda: _disc([0], [1], number_splits=0))),
    A("disc-equal-bounds", "high[0]=0 must be greater than low[0]=0 (each dimension needs high > low)",
      raises(lambda: _disc([0], [0]))),
    A("disc-nan-bound", "low=[nan]: every value must be finite", raises(lambda: _disc([float("nan")], [1]))),
    A("disc-empty", "low=[]: expected at least one value", raises(lambda: _disc([], []))),
    A("disc-bounds-not-list", "low=0.5: expected a list of numbers", raises(lambda: _disc(0.5, [1]))),
    A("disc-mode", "mode='hash': allowed values are bins, round, edges", raises(lambda: _disc([0], [1], mode="hash"))),
    A("disc-round-resolution", "resolution=0: expected a finite number > 0",
      raises(lambda: _disc([0], [1], mode="round", resolution=0))),
    A("disc-edges-unsorted", "edges[0]=[1.0, 0.0]: edges must be strictly increasing",
      raises(lambda: _disc([0], [1], mode="edges", edges=[[1, 0]]))),
    A("disc-edges-none", "mode='edges' needs edges: one list of edges per dimension (1 lists",
      raises(lambda: _disc([0], [1], mode="edges"))),
    A("disc-edges-ragged-count", "one list of edges per dimension (2 lists",
      raises(lambda: _disc([0, 0], [1, 1], mode="edges", edges=[[0.5]]))),
    A("disc-state-overflow", "number_splits=[65536, 65536]: 65536 x 65536 = 4.29e+09 states, more than",
      raises(lambda: _disc([0, 0], [1, 1], number_splits=[65536, 65536]))),
    A("parse-overrides-no-equals", "--set 'alpha': expected KEY=VALUE", raises(lambda: parse_overrides(["alpha"]))),
    A("yaml-duplicate-key", "duplicate key 'a' (lines 1 and 2)", _yaml_file("a: 1\na: 2\n")),
    A("yaml-python-tag", "could not determine a constructor", _yaml_file("a: !!python/name:os.system\n")),
    A("yaml-malformed", "not valid YAML", _yaml_file("a: [1\n")),
    A("yaml-missing-file", "config file not found", lambda tmp: load_yaml(os.path.join(tmp, "absent.yaml"))),
]

CPC, TWIST = "CartPoleContinuous-v0", "QuadcopterGotoTwist-v0"


def D(id: str, fragment: str, *argv: str, agent: str = "ppo", env: str = CPC) -> Case:  # noqa: N802 - a table row
    """A ``--agent ppo|sac`` row (Brax's trainers): refused before anything compiles, like the tabular rows."""
    return Case(f"train-{agent}-{id}", "train", ("--env", env, "--agent", agent) + argv, fragment)


DEEP = [
    D("on-discrete-id", "QuadcopterGoto-v1 has a Discrete(5) action space", env=GOTO),
    Case("train-tabular-on-box-id", "train", ("--env", TWIST, "--agent", "qlearn"),
         "has continuous (Box) actions; use --agent ppo or --agent sac"),
    D("learning-rate-range", "learning_rate=2.0: expected a number > 0.0 and <= 1.0", "--set", "learning_rate=2"),
    D("discounting-range", "discounting=1.5: expected a number >= 0.0 and <= 1.0", "--set", "discounting=1.5"),
    D("num-envs-zero", "num_envs=0: expected an integer >= 1", "--n-envs", "0"),
    D("batch-not-multiple", "must be a multiple of num_envs=2048", "--set", "batch_size=100"),
    D("layers-bad", "policy_hidden_layer_sizes=[0]: expected a non-empty list of integers >= 1",
      "--set", "policy_hidden_layer_sizes=[0]"),
    D("unknown-key", "unknown key 'tau'", "--set", "tau=0.1"),
    D("nepisodes", "--nepisodes: --agent ppo trains for a number of env steps", "--nepisodes", "3"),
    D("unknown-preset", "preset='fast': allowed values are default, tiny", "--preset", "fast"),
    D("replay-too-large", "min_replay_size=10 must be < total_steps=5", "--set", "min_replay_size=10",
      "--total-steps", "5", agent="sac"),
    D("resume-with-config-flags", "the run goes on with its own config.yaml and directory; drop --env, --agent",
      "--resume", "{tmp}"),
    D("total-steps-twice", "total_steps given twice: --total-steps 10 and --set num_timesteps=20", "--total-steps",
      "10", "--set", "num_timesteps=20"),
    D("total-steps-alias-and-name", "name the same setting (num_timesteps is the old name of total_steps)",
      "--set", "num_timesteps=20", "--set", "total_steps=10"),
    D("sac-tau-range", "tau=0.0: expected a number > 0.0 and <= 1.0", "--set", "tau=0", agent="sac"),
    # Brax's trainer runs on one device and counts env steps: these tabular flags were silently ignored.
    D("devices", "--devices: --agent ppo trains on one device", "--devices", "4"),
    D("sac-devices", "--devices: --agent sac trains on one device", "--devices", "1", agent="sac"),
    D("total-episodes", "--total-episodes: --agent ppo trains for a number of env steps", "--total-episodes", "5"),
]

def _check_out(path: str) -> Any:
    from jaxrobo.io import rundir

    return rundir.check_out(path)


CASES = TRAIN + SWEEP + PLOT + SHOW + EVAL + EXPORT + LIST + CHECK + API + DEEP


# ---- the runner -------------------------------------------------------------------------------------------------
@pytest.fixture(autouse=True)
def nothing_runs(monkeypatch):
    """Whatever got past validation would reach one of these; each fails the case instead of training/drawing."""
    import matplotlib.figure

    from jaxrobo import show as flights
    from jaxrobo.io import results
    from jaxrobo.training import train
    from jaxrobo.training import trainer as trainer_module
    from jaxrobo.training.sweep import running as sweep_running

    def forbidden(what: str):
        def fail(*_a, **_kw):
            raise AssertionError(f"{what} was reached: the input was not refused at validation")
        return fail

    from jaxrobo import deep

    monkeypatch.setattr(deep, "train", forbidden("deep.train (Brax's trainer)"))

    _REAL["train"] = train.train
    monkeypatch.setattr(train, "train", forbidden("train()"))
    monkeypatch.setattr(trainer_module.Trainer, "init", forbidden("Trainer.init"))
    monkeypatch.setattr(sweep_running, "GroupRunner", forbidden("the sweep's compiled group"))
    monkeypatch.setattr(flights, "fly", forbidden("flights.fly"))
    monkeypatch.setattr(flights, "episodes", forbidden("show.episodes"))
    from jaxrobo import evaluate

    monkeypatch.setattr(evaluate, "evaluate", forbidden("eval's rollouts"))
    monkeypatch.setattr(results, "save_run", forbidden("save_run"))
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", forbidden("savefig"))


def _files(root: str) -> set[str]:
    return {os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs} | {d for d, _, _ in os.walk(root)}


def _sub(x: Any, tmp: str) -> Any:
    return x.replace("{tmp}", tmp) if isinstance(x, str) else x


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_refused_naming_the_field(case: Case, tmp_path, monkeypatch, capsys):
    tmp = str(tmp_path)
    if case.setup is not None:
        case.setup(tmp, monkeypatch)
    before = _files(tmp)
    capsys.readouterr()
    fragment = _sub(case.fragment, tmp)
    if case.command == "api":
        with pytest.raises((ConfigError, ValueError, TypeError)) as err:
            case.args(tmp)
        assert fragment in str(err.value), str(err.value)
    else:
        argv = [case.command] + [_sub(a, tmp) for a in case.args]
        if case.command in ("train", "sweep") and case.out:
            argv += ["--out", os.path.join(tmp, "out")]
        if case.command == "train":
            argv.append("--no-progress")
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's own usage errors (one line too: jaxrobo.core.cliargs.Parser)
            code = exc.code
        out, err = capsys.readouterr()
        assert code == case.code, (code, out, err)
        assert "Traceback" not in err + out
        assert fragment in err, err
        assert not os.path.exists(os.path.join(tmp, "out"))
        assert case.code == 0 or len([ln for ln in err.splitlines() if ln.strip()]) == 1, err  # one line
    assert _files(tmp) == before, sorted(_files(tmp) - before)


def test_the_table_is_large_and_its_ids_unique():
    assert len(CASES) >= 110
    assert len({c.id for c in CASES}) == len(CASES)
    assert {c.command for c in CASES} == {"train", "sweep", "plot", "show", "eval", "export", "list", "check", "api"}


@pytest.mark.parametrize("argv, line", [
    (["eval", "RUN", "--episodes", "x"], "jaxrobo eval: argument --episodes: invalid int value: 'x'"),
    (["export", "RUN", "--out", "o", "--table", "first"], "jaxrobo export: argument --table: invalid int value: "
                                                            "'first'"),
    (["export", "RUN"], "jaxrobo export: the following arguments are required: --out"),
    (["ros", "sim", "--bogus"], "jaxrobo ros sim: the following arguments are required: ID"),
    (["ros", "sim", "CartPoleStayUp-v0", "--bogus"], "jaxrobo ros sim: unrecognized arguments: --bogus"),
    (["nosuch"], "jaxrobo: argument command: invalid choice: 'nosuch' (choose from"),
])
def test_a_usage_error_of_any_subcommand_is_one_line_exit_2(argv, line, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "" and len(err.splitlines()) == 1 and err.startswith(line), err


def test_a_sweep_parser_of_its_own_is_one_line_too(capsys):
    from jaxrobo.training.sweep.cli import main as sweep_main

    with pytest.raises(SystemExit) as exc:
        sweep_main(["--seeds", "1e3"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err == "jaxrobo sweep: argument --seeds: invalid int value: '1e3'\n", err


@pytest.mark.parametrize("argv", [["--help"], ["train", "--help"], ["ros", "sim", "--help"]])
def test_help_still_prints_the_usage(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out, err = capsys.readouterr()
    assert exc.value.code == 0 and out.startswith(f"usage: jaxrobo {' '.join(argv[:-1])}".rstrip()) and err == ""


def test_help_never_touches_an_unusable_cache(tmp_path, monkeypatch, capsys):
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("JAXROBO_CACHE_DIR", str(tmp_path / "file" / "sub"))
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out, err = capsys.readouterr()
    assert "usage: jaxrobo" in out and err == ""


def test_nothing_named_by_a_file_was_imported():
    """The env_id 'module:Id' cases above wrote a module that would have been imported by a lax reader."""
    import sys

    assert EVIL not in sys.modules


def test_numbers_in_every_float_syntax_are_accepted():
    """``--set alpha=1e-3`` is the number 0.001 (YAML 1.1 alone reads it as a string)."""
    assert parse_overrides(["alpha=1e-3", "gamma=9.9E-1", "epsilon=.5e-1", "nsteps=1e3", "bins=[1e0, 2]"]) == {
        "alpha": 0.001, "gamma": 0.99, "epsilon": 0.05, "nsteps": 1000.0, "bins": [1.0, 2]}
    spec = _resolve(CP, overrides={"alpha": 1e-3, "nsteps": 1e3})
    assert spec.agent_params.alpha == 0.001 and spec.config.nsteps == 1000


def test_list_still_lists_every_env_with_a_broken_agent_yaml(tmp_path, monkeypatch, capsys):
    import jaxrobo

    agent_yaml("default: [1, 2\n")(str(tmp_path), monkeypatch)
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert all(env_id in out for env_id in jaxrobo.registered())
    assert "agent YAML unreadable" in out
