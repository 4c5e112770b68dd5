"""A deep run's checkpoint: the trainer's whole state at its last evaluation point, or at the end of a host iteration
between points (:class:`jaxrobo.deep.training.EpochPlan`), and the run's record so far, in the run directory's
``checkpoint.npz`` (:data:`jaxrobo.io.rundir.CHECKPOINT`), rewritten atomically each time.

What is saved (:func:`save`): the state tuple Brax's epoch left (:class:`jaxrobo.interop.brax_compat.EpochHook`:
PPO's ``TrainingState`` (optimiser state, policy and value parameters, observation normaliser, env step count) and
the training envs' state; SAC's the same plus its replay buffer) as plain arrays by leaf (``state_<i>``; a PRNG key
as its key data), the number of epochs done and of host iterations done of the next (with their training metrics),
the evaluations so far (``eval_*``), Brax's training metrics, and a
fingerprint (:func:`fingerprint`: the resolved config, the JAX and Brax versions, the sources' hash). Brax's own
``checkpoint.save`` (orbax) keeps the parameters only, which cannot continue a run; the saved policy files
(``policy.npz``, ``best/policy.npz``) are the run's parameters in :mod:`jaxrobo.deep.policy`'s format.

:func:`load` reads it back as a :class:`Saved`, refusing (a :class:`~jaxrobo.training.checkpoint.CheckpointError`
naming the file) one of another config or code, or whose arrays are missing, misshapen or not finite;
:func:`restore_states` puts the saved state in place of a fresh one of the same structure (the trainer's own, at
its first epoch), refusing a leaf of another name, shape or dtype.
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np

from jaxrobo.core.config import parse_json
from jaxrobo.training.checkpoint import CheckpointError, fingerprint_mismatch, read_npz, write_npz

#: Bumped when the layout changes.
FORMAT = 2
#: The evaluation arrays kept per point (``success`` only for a task with one).
EVAL_FIELDS = ("return", "length", "terminated", "success")


def fingerprint(spec: Any) -> dict[str, Any]:
    """What a checkpoint must match to be resumed: the run's resolved config and the code that ran it."""
    import jax

    from jaxrobo.core.version import __version__, source_hash
    from jaxrobo.interop.brax_compat import installed_version

    return json.loads(json.dumps({"format": FORMAT, "config": spec.to_dict(), "jaxrobo": __version__,
                                  "jax": jax.__version__, "brax": installed_version(),
                                  "sources": source_hash()}))


@dataclasses.dataclass
class Saved:
    """A loaded checkpoint: ``epochs_done`` of the trainer and ``chunks_done`` host iterations of the next (with
    their Brax metrics, ``partial_metrics``), its ``states`` (host leaves in flatten order, None when nothing
    trained), the ``evaluations`` and ``training_metrics`` so far (as :class:`DeepResult` holds them) and
    ``train_seconds`` (training wall time before the stop, evaluations excluded)."""

    epochs_done: int
    states: list[np.ndarray] | None
    key_impls: list[str | None]
    names: list[str]
    evaluations: list[dict[str, Any]]
    training_metrics: list[dict[str, float]]
    train_seconds: float
    chunks_done: int = 0
    partial_metrics: list[dict[str, float]] = dataclasses.field(default_factory=list)


def _is_key(x: Any) -> bool:
    import jax

    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _flat(states: Any) -> tuple[list[Any], list[str], Any]:
    import jax

    from jaxrobo.deep.policy import _path_name

    paths, treedef = jax.tree_util.tree_flatten_with_path(states)
    return [x for _, x in paths], [_path_name(p) for p, _ in paths], treedef


def save(path: str, fp: dict[str, Any], epochs_done: int, states: Any, evaluations: list[dict[str, Any]],
         training_metrics: list[dict[str, float]], train_seconds: float, chunks_done: int = 0,
         partial_metrics: list[dict[str, float]] = ()) -> None:
    """Write the checkpoint (see the module docstring) atomically; ``states`` are the device arrays the last host
    iteration left (None before the first)."""
    import jax

    arrays: dict[str, Any] = {}
    names: list[str] = []
    impls: list[str | None] = []
    if states is not None:
        leaves, names, _ = _flat(states)
        impls = [str(jax.random.key_impl(x)) if _is_key(x) else None for x in leaves]
        host = jax.device_get([jax.random.key_data(x) if _is_key(x) else x for x in leaves])
        arrays.update({f"state_{i}": np.asarray(x) for i, x in enumerate(host)})
    if evaluations:
        arrays["eval_env_steps"] = np.asarray([e["env_steps"] for e in evaluations], np.int64)
        arrays["eval_seconds"] = np.asarray([e["seconds"] for e in evaluations], np.float64)
        for field in EVAL_FIELDS:
            if field in evaluations[0]:
                arrays[f"eval_{field}"] = np.stack([np.asarray(e[field]) for e in evaluations])
    meta = {"fingerprint": fp, "epochs_done": int(epochs_done), "has_states": states is not None,
            "state_names": names, "key_impls": impls, "training_metrics": training_metrics,
            "train_seconds": float(train_seconds), "chunks_done": int(chunks_done),
            "partial_metrics": list(partial_metrics)}
    write_npz(path, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)


def load(path: str, fp: dict[str, Any], plan: Any, eval_episodes: int) -> Saved:
    """The checkpoint at ``path``, checked against this run's :func:`fingerprint` ``fp``, its
    :class:`~jaxrobo.deep.training.EpochPlan` and number of evaluation episodes; :class:`CheckpointError` saying
    what is wrong."""
    import zipfile

    try:
        data = read_npz(path, "the checkpoint")
    except (zipfile.BadZipFile, EOFError, KeyError, MemoryError) as err:  # a truncated or corrupted file
        raise CheckpointError(f"{path}: cannot read the checkpoint ({type(err).__name__}: {err})") from None

    def bad(what: str) -> CheckpointError:
        return CheckpointError(f"{path}: {what}")

    try:
        meta = parse_json(str(data["meta"]))
        epochs_done, has_states = int(meta["epochs_done"]), bool(meta["has_states"])
        names, impls = list(meta["state_names"]), list(meta["key_impls"])
        metrics = [{str(k): float(v) for k, v in m.items()} for m in meta["training_metrics"]]
        chunks_done = int(meta["chunks_done"])
        partial = [{str(k): float(v) for k, v in m.items()} for m in meta["partial_metrics"]]
        train_seconds = float(meta["train_seconds"])
        saved_fp = meta["fingerprint"]
    except (KeyError, ValueError, TypeError, AttributeError) as err:
        raise bad(f"not a jaxrobo deep-RL checkpoint ({type(err).__name__}: {err})") from None
    why = fingerprint_mismatch(saved_fp, fp)
    if why is None and saved_fp.get("brax") != fp.get("brax"):
        why = f"it was written with brax {saved_fp.get('brax')} (this is {fp.get('brax')})"
    if why is not None:
        raise bad(f"refusing to resume: {why}")
    if (not 0 <= epochs_done <= plan.epochs or not 0 <= chunks_done < plan.chunks
            or (epochs_done == plan.epochs and chunks_done) or len(partial) != chunks_done
            or has_states != (epochs_done > 0 or chunks_done > 0) or len(names) != len(impls)):
        raise bad(f"epochs_done={epochs_done}, chunks_done={chunks_done} do not fit a run of {plan.epochs} epochs "
                  f"of {plan.chunks} host iterations (or its state list is inconsistent)")
    states = None
    if has_states:
        states = []
        for i in range(len(names)):
            x = data.get(f"state_{i}")
            if x is None:
                raise bad(f"state leaf {i} ({names[i]}) is missing")
            if x.dtype.kind == "f" and not np.all(np.isfinite(x)):
                raise bad(f"state leaf {names[i]} holds non-finite values; the run it saved diverged")
            states.append(x)
    n = plan.points(epochs_done)
    evaluations: list[dict[str, Any]] = []
    steps, seconds = data.get("eval_env_steps"), data.get("eval_seconds")
    if steps is None or seconds is None or steps.shape != (n,) or seconds.shape != (n,):
        raise bad(f"expected {n} evaluation points (eval_env_steps, eval_seconds) after {epochs_done} epochs")
    if steps.dtype.kind not in "iu" or np.any(np.diff(steps) <= 0) or np.any(steps < 0):
        raise bad("eval_env_steps must be increasing counts of env steps")
    fields = {}
    for field in EVAL_FIELDS:
        x = data.get(f"eval_{field}")
        if x is None:
            if field == "success":
                continue
            raise bad(f"eval_{field} is missing")
        if x.shape != (n, eval_episodes) or (x.dtype.kind == "f" and not np.all(np.isfinite(x))):
            raise bad(f"eval_{field} has shape {x.shape}, expected ({n}, {eval_episodes}) finite values")
        fields[field] = x
    for i in range(n):
        row = {field: x[i] for field, x in fields.items()}
        row["env_steps"], row["seconds"] = int(steps[i]), float(seconds[i])
        evaluations.append(row)
    return Saved(epochs_done, states, impls, names, evaluations, metrics, train_seconds, chunks_done, partial)


def restore_states(path: str, saved: Saved, fresh: tuple) -> tuple:
    """``saved``'s state in the structure of ``fresh`` (the trainer's own freshly initialised state tuple, with
    its leading device axis); :class:`CheckpointError` naming the first leaf whose name, shape or dtype differs."""
    import jax

    leaves, names, treedef = _flat(fresh)
    if names != saved.names:
        diff = next((f"{a!r} vs {b!r}" for a, b in zip(saved.names, names) if a != b),
                    f"{len(saved.names)} leaves vs {len(names)}")
        raise CheckpointError(f"{path}: the saved trainer state does not have this trainer's structure ({diff})")
    out = []
    for name, leaf, x, impl in zip(names, leaves, saved.states, saved.key_impls):
        value = jax.random.wrap_key_data(x, impl=impl) if impl is not None else x
        if value.shape != leaf.shape or value.dtype != leaf.dtype:
            raise CheckpointError(f"{path}: state leaf {name} is {value.dtype}{list(value.shape)}, the trainer's "
                                  f"is {leaf.dtype}{list(leaf.shape)}")
        out.append(value)
    return tuple(jax.tree_util.tree_unflatten(treedef, out))
