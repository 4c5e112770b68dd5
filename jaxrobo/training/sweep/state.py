"""A sweep's saved progress: finished groups survive an interrupt or a crash.

While a sweep runs, its state directory holds ``sweep_state.json`` (the settings of the
:class:`~jaxrobo.training.sweep.planning.SweepPlan`, the code's versions and their fingerprint: :func:`open_state`) and
``checkpoint.npz`` (the row metrics of every finished group: :func:`save_checkpoint`, read back by
:func:`load_checkpoint`) and, for the group in progress, ``group_<g>.npz``: its whole carry (every row's tables,
envs and records) at a chunk boundary (:func:`save_group_carry`, :func:`load_group_carry`), so that a resumed
sweep goes on inside that group from its last saved chunk. A state saved by other settings or other code is
refused, naming what differs; a group carry is read as a hostile file (:func:`jaxrobo.io.npz.read_npz`) and
checked against the sweep's fingerprint, the group and the carry's shapes before it is used.

Public surface: :data:`STATE_FILE`, :data:`STATE_FORMAT`, :func:`code_version`, :func:`read_state`,
:func:`open_state`, :func:`save_checkpoint`, :func:`load_checkpoint`, :func:`group_carry_path`,
:func:`save_group_carry`, :func:`check_group_carry`, :func:`load_group_carry`,
:func:`drop_group_carry`.
"""
from __future__ import annotations

import json
import os
from typing import Any, Mapping

import jax
import numpy as np

from jaxrobo.training import checkpoint
from jaxrobo.core.config import ConfigError
from jaxrobo.training.sweep.planning import SweepPlan, _canonical

STATE_FILE = "sweep_state.json"
STATE_FORMAT = 1


def code_version() -> dict[str, str]:
    """What the sweep's numbers depend on besides its settings: jaxrobo's sources and the libraries' versions."""
    from importlib import metadata

    from jaxrobo.core.version import __version__
    from jaxrobo.core.version import source_hash

    out = {"jaxrobo": __version__, "jaxrobo_sources": source_hash()}
    for dist in ("jax", "jaxlib", "numpy", "mujoco", "mujoco-mjx", "brax"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    return out


def read_state(state_dir: str) -> dict[str, Any]:
    """The saved ``sweep_state.json`` of ``state_dir``: settings, versions, fingerprint and extra."""
    path = os.path.join(state_dir, STATE_FILE)
    from jaxrobo.core.config import check_regular, parse_json

    check_regular(path)  # a FIFO would hang the read, a device never end it
    try:
        with open(path) as f:
            state = parse_json(f.read())
    except FileNotFoundError:
        raise ConfigError(f"{state_dir}: not a sweep ({STATE_FILE} missing)") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: unreadable sweep state ({err})") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        raise ConfigError(f"{path}: not a sweep state this jaxrobo reads (format {found!r}, expected {STATE_FORMAT})")
    return state


def open_state(state_dir: str, plan: SweepPlan, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The saved state of ``plan`` in ``state_dir``: checked to be this sweep's (same settings and code) if there
    is one, else written (process 0). Raises :class:`ConfigError` saying what differs."""
    import hashlib

    from jaxrobo.io import rundir

    versions = code_version()
    fingerprint = hashlib.sha256(json.dumps([plan.settings, versions], sort_keys=True).encode()).hexdigest()
    if os.path.exists(os.path.join(state_dir, STATE_FILE)):
        state = read_state(state_dir)
        if state.get("fingerprint") != fingerprint:
            old_v, old_s = state.get("versions", {}), state.get("settings", {})
            code = [k if k == "jaxrobo_sources" else f"{k} {old_v.get(k)} → {versions[k]}"
                    for k in versions if old_v.get(k) != versions[k]]
            diff = sorted(k for k in set(plan.settings) | set(old_s) if plan.settings.get(k) != old_s.get(k))
            why = (f"by other code ({', '.join(code)} changed)" if code else
                   f"by a sweep with other settings ({', '.join(diff) or 'fingerprint'} differ)")
            raise ConfigError(f"{state_dir}: cannot resume: its sweep state was saved {why}; "
                              "start it again with --overwrite, or sweep into another --out")
        return state
    state = {"format": STATE_FORMAT, "fingerprint": fingerprint, "versions": versions, "settings": plan.settings,
             "extra": _canonical(dict(extra or {}))}
    if jax.process_index() == 0:
        rundir.atomic_write_json(os.path.join(state_dir, STATE_FILE), state)
    return state


def save_checkpoint(state_dir: str, fingerprint: str, plan: SweepPlan, finished: Mapping[int, Mapping[str, Any]]
                    ) -> None:
    """The row metrics of every finished group in ``state_dir/checkpoint.npz`` (plain arrays, no pickle), written
    atomically (:func:`jaxrobo.training.checkpoint.write_npz`): a crash leaves the previous checkpoint or this one."""
    from jaxrobo.io import rundir

    arrays: dict[str, np.ndarray] = {"fingerprint": np.asarray(fingerprint),
                                     "finished": np.asarray(sorted(finished), np.int64)}
    for g, done in finished.items():
        p = plan.groups[g]
        arrays[f"g{g}_config"] = np.asarray([i for i, _, _ in p.meta], np.int64)
        arrays[f"g{g}_seed"] = np.asarray([s for _, s, _ in p.meta], np.int64)
        for k in ("compile_seconds", "run_seconds", "eval_seconds", "slot_steps", "start_chunk",
                  "restored_env_steps"):
            arrays[f"g{g}_{k}"] = np.asarray(done.get(k, 0.0), np.float64)
        arrays[f"g{g}_complete"] = np.asarray(bool(done["complete"]))
        arrays.update({f"g{g}_metric_{k}": np.asarray(v) for k, v in done["metrics"].items()})
    checkpoint.write_npz(os.path.join(state_dir, rundir.CHECKPOINT), **arrays)


def load_checkpoint(state_dir: str, plan: SweepPlan, fingerprint: str) -> dict[int, dict[str, Any]]:
    """The finished groups saved in ``state_dir``: ``{group: {"metrics", "compile_seconds", "run_seconds",
    "complete"}}`` (empty without a checkpoint). Raises :class:`ConfigError` for one of another sweep."""
    from jaxrobo.io import rundir

    path = os.path.join(state_dir, rundir.CHECKPOINT)
    if not os.path.exists(path):
        return {}
    data = checkpoint.read_npz(path, "the sweep checkpoint")
    if str(data.get("fingerprint")) != fingerprint:
        raise ConfigError(f"{path}: saved by another sweep than {os.path.join(state_dir, STATE_FILE)}; "
                          "start it again with --overwrite")
    out = {}
    try:
        for g in (int(x) for x in np.asarray(data["finished"]).reshape(-1)):
            if not 0 <= g < len(plan.groups):
                raise ValueError(f"group {g} is not one of the sweep's {len(plan.groups)} groups")
            p = plan.groups[g]
            if not (np.array_equal(data[f"g{g}_config"], [i for i, _, _ in p.meta])
                    and np.array_equal(data[f"g{g}_seed"], [s for _, s, _ in p.meta])):
                raise ConfigError(f"{path}: group {g} holds other rows than the sweep plans")
            prefix = f"g{g}_metric_"
            metrics = {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)}
            if any(np.shape(v)[:1] != (len(p.meta),) for v in metrics.values()):
                raise ValueError(f"group {g}: metrics of another number of rows than its {len(p.meta)}")
            out[g] = {"metrics": metrics, "compile_seconds": float(data[f"g{g}_compile_seconds"]),
                      "run_seconds": float(data[f"g{g}_run_seconds"]), "complete": bool(data[f"g{g}_complete"]),
                      "slot_steps": float(data.get(f"g{g}_slot_steps", 0.0)),
                      "eval_seconds": float(data.get(f"g{g}_eval_seconds", 0.0)),
                      "start_chunk": int(data.get(f"g{g}_start_chunk", 0)),
                      "restored_env_steps": int(data.get(f"g{g}_restored_env_steps", 0))}
    except (KeyError, ValueError, TypeError) as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"{path}: not a checkpoint of this sweep ({type(err).__name__}: {err}); start it again "
                          "with --overwrite") from None
    return out


# ---- the carry of the group in progress ---------------------------------------------------------------------------
def group_carry_path(state_dir: str, group: int) -> str:
    """Where group ``group``'s carry is saved while it runs (``group_<g>.npz`` beside ``checkpoint.npz``)."""
    return os.path.join(state_dir, f"group_{int(group)}.npz")


def _carry_fingerprint(fingerprint: str, group: int, carry: Any) -> dict[str, Any]:
    """What a group's carry must match: the sweep's fingerprint (settings and code), the group, and the carry's
    structure and leaf shapes (:func:`jaxrobo.training.checkpoint.carry_fingerprint`)."""
    return checkpoint.carry_fingerprint(carry, {"sweep": fingerprint, "group": int(group)})


def save_group_carry(state_dir: str, fingerprint: str, group: int, carry: Any, chunks_done: int) -> None:
    """Group ``group``'s carry after ``chunks_done`` chunks to :func:`group_carry_path`, atomically
    (:func:`jaxrobo.training.checkpoint.save_checkpoint`: plain arrays, keys as their data)."""
    checkpoint.save_checkpoint(group_carry_path(state_dir, group), carry, chunks_done,
                               _carry_fingerprint(fingerprint, group, carry))


def load_group_carry(state_dir: str, fingerprint: str, group: int, template: Any) -> tuple[Any, int] | None:
    """Group ``group``'s saved carry and its chunk count, or None when none is saved. ``template``: a carry of
    the group's structure (its fresh ``init``). A file that is unreadable, of another sweep, group or carry
    shape raises :class:`ConfigError` naming it, and how to start the group over."""
    path = group_carry_path(state_dir, group)
    if not os.path.exists(path):
        return None
    try:
        return checkpoint.load_checkpoint(path, template, _carry_fingerprint(fingerprint, group, template))
    except ConfigError as err:
        raise ConfigError(f"{err} (remove {path} to run group {group + 1} from its first chunk)") from None


def check_group_carry(state_dir: str, fingerprint: str, group: int) -> None:
    """Before anything compiles: group ``group``'s saved carry (where one is saved) is a whole checkpoint of this
    sweep and group, written by this jaxrobo, JAX and source code. :class:`ConfigError` naming the file and how to
    start the group over otherwise; the carry's structure and shapes are checked when it is loaded
    (:func:`load_group_carry`, which needs the group's traced template)."""
    path = group_carry_path(state_dir, group)
    if not os.path.exists(path):
        return
    try:
        saved, _ = checkpoint.read_fingerprint(path)
        expected = checkpoint.carry_fingerprint([], {"sweep": fingerprint, "group": int(group)})
        known = {k: v for k, v in expected.items() if k not in ("treedef", "leaves")}  # need the template
        why = checkpoint.fingerprint_mismatch({k: saved.get(k) for k in known} if isinstance(saved, dict) else {},
                                              known)
        if why:
            raise ConfigError(f"{path}: refusing to resume from it: {why}")
    except ConfigError as err:
        raise ConfigError(f"{err} (remove {path} to run group {group + 1} from its first chunk)") from None


def drop_group_carry(state_dir: str, group: int) -> None:
    """Remove group ``group``'s carry once its metrics are saved (the group is finished)."""
    try:
        os.remove(group_carry_path(state_dir, group))
    except FileNotFoundError:
        pass
