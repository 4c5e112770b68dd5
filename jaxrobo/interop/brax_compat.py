"""The three places where jaxrobo reaches past Brax's public surface, guarded by the Brax version they were written for.

1. :func:`install_jax_compat`: Brax 0.14's trainers call ``jax.device_put_replicated`` and
   ``jax.device_put_sharded``, which JAX 0.10 removed. Where JAX lacks them, this sets the drop-in replacements of
   JAX's pmap migration guide on the ``jax`` module (a leading device axis, one shard per device); where JAX still
   has them it does nothing. :mod:`jaxrobo.interop.brax_env` calls it on import, so ``ppo.train`` and ``sac.train`` run
   unchanged on a BraxEnv.
2. :func:`keep_evaluator_params`: Brax's SAC takes no ``policy_params_fn``; it hands the parameters of each
   evaluation point to the ``brax.training.acting.Evaluator`` it builds. For the length of a ``with`` block this
   swaps that class (looked up on the module by ``sac.train``) for one that keeps the parameters and skips Brax's
   own evaluation rollout, and puts the original back on the way out, also when training raises. The swap is
   process-wide for its duration: do not run another Brax trainer in another thread meanwhile.

3. :func:`hook_epochs`: Brax's trainers keep their whole state (optimiser state, normaliser, parameters, env
   state, SAC's replay buffer) and their random keys inside one call; their ``restore_params`` /
   ``restore_checkpoint_path`` put back the parameters only. For the length of a ``with`` block this gives the
   trainer module (``brax.training.agents.ppo.train`` or ``...sac.train``) a ``jax`` whose ``pmap`` wraps the
   function named ``training_epoch`` (every other name passes through unchanged): each epoch's random keys are
   jaxrobo's own (``epoch_keys(i, n_devices)`` of the epoch's index over the whole run), the state the epoch leaves
   is kept (:attr:`EpochHook.states`), and a resumed run's saved state replaces the fresh one at its first epoch.
   The first epoch's state is put on the sharding the mapped epoch gives its outputs, so the epoch is compiled
   once; given ``compile_epoch``, every epoch runs the program it returns (jaxrobo's kept trace of the epoch).
   The swap is of that module's global only and is undone on the way out, also when training raises.
   :func:`advance_epoch_keys` gives the key a Brax epoch carries after some of its training steps, so one epoch
   can run as several shorter ones with the same random numbers.

All three follow Brax's internals, so they are guarded: :data:`WRITTEN_FOR` is the range of ``brax`` versions they were
written and tested for. Outside it (or where ``acting.Evaluator`` does not have the shape the swap needs),
:func:`unavailable` gives the reason, and:

* :func:`install_jax_compat` still fills in the missing JAX functions (adding a name JAX no longer has cannot
  change a library that does not call it, and a Brax that still calls them needs them) and warns once with a
  :class:`RuntimeWarning` that the combination is untested;
* :func:`keep_evaluator_params` raises :class:`BraxCompatError` naming the version before anything trains where
  the Evaluator is not what it replaces, and warns once where only the version is outside the range; if the
  trainer then never handed parameters to the evaluator, :meth:`EvaluatorHook.check` says so with the version
  instead of leaving the run without evaluations.

To widen the range, run ``tests/test_brax_compat.py``, ``tests/test_brax_env.py``, ``tests/test_deep.py``,
``tests/test_deep_resume.py`` (resume bit for bit) and ``tests/test_deferred_imports.py`` (the range guards
:mod:`jaxrobo.interop.deferred_imports` too) on the new version. Public surface: :data:`WRITTEN_FOR`,
:func:`installed_version`, :func:`unavailable`, :func:`install_jax_compat`, :func:`keep_evaluator_params`,
:class:`EvaluatorHook`, :func:`hook_epochs`, :class:`EpochHook`, :func:`advance_epoch_keys`,
:class:`BraxCompatError`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core.version import installed, outside, warn_once

#: The ``brax`` versions both tricks were written and tested for: ``[low, high)`` as (major, minor).
WRITTEN_FOR = ((0, 14), (0, 15))
#: The JAX functions Brax's trainers call that JAX 0.10 removed.
JAX_FUNCTIONS = ("device_put_replicated", "device_put_sharded")

_WARNED: set[str] = set()


class BraxCompatError(RuntimeError):
    """The installed Brax does not have the internals a jaxrobo trick needs (the message names the version)."""


def installed_version() -> str | None:
    """The installed ``brax`` version string, or None if its metadata cannot be found."""
    return installed("brax")


def unavailable(version: str | None = None) -> str | None:
    """Why the tricks are outside what they were written for (a sentence), or None when they are not.
    ``version`` defaults to :func:`installed_version`."""
    version = installed_version() if version is None else version
    return outside("brax", version, WRITTEN_FOR, "jaxrobo.interop.brax_compat")


def _sharding(devices: Any) -> Any:
    mesh = jax.sharding.Mesh(np.asarray(devices), ("devices",))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("devices"))


def device_put_replicated(x: Any, devices: Any) -> Any:
    """JAX's removed ``device_put_replicated``: each leaf stacked once per device along a new leading axis."""
    s = _sharding(devices)
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), s), x)


def device_put_sharded(shards: Any, devices: Any) -> Any:
    """JAX's removed ``device_put_sharded``: the i-th of ``shards`` on the i-th device, along a new leading axis."""
    s = _sharding(devices)
    return jax.tree.map(lambda *xs: jax.device_put(jnp.stack([jnp.asarray(a) for a in xs]), s), *shards)


def install_jax_compat(version: str | None = None) -> list[str]:
    """Set the JAX functions of :data:`JAX_FUNCTIONS` that JAX lacks (see the module docstring); return the names
    it set (empty where JAX has them all: then it does nothing, whatever the Brax version). ``version`` (the Brax
    version to check, default the installed one) exists so the guard can be tested."""
    missing = [name for name in JAX_FUNCTIONS if not hasattr(jax, name)]
    if not missing:
        return []
    reason = unavailable(version)
    if reason is not None:
        warn_once(_WARNED, f"jaxrobo.interop.brax_compat: {reason}; setting jax.{' and jax.'.join(missing)} "
                  "(removed in JAX 0.10) for it anyway, untested with this Brax")
    for name in missing:
        setattr(jax, name, globals()[name])
    return missing


@dataclasses.dataclass
class EvaluatorHook:
    """What :func:`keep_evaluator_params` yields: :meth:`pop` the parameters the trainer handed to its evaluator
    since the last call (None if none); ``calls`` counts the hand-overs."""

    version: str | None
    calls: int = 0
    _params: Any = None
    _has: bool = False

    def keep(self, params: Any) -> None:
        self.calls += 1
        self._params, self._has = params, True

    def pop(self) -> Any:
        params, self._params, self._has = self._params, None, False
        return params

    @property
    def has_params(self) -> bool:
        return self._has

    def check(self) -> None:
        """Raise :class:`BraxCompatError` if the trainer never handed parameters to its evaluator (a Brax whose
        trainer no longer builds ``acting.Evaluator`` as the swap expects)."""
        if self.calls == 0:
            raise BraxCompatError(f"brax {self.version}: sac.train never handed its parameters to "
                                  "brax.training.acting.Evaluator.run_evaluation, so the run has no evaluations; "
                                  f"jaxrobo.interop.brax_compat was written for brax {_range()}")


def _range() -> str:
    low, high = WRITTEN_FOR
    return f">= {low[0]}.{low[1]}, < {high[0]}.{high[1]}"


@contextlib.contextmanager
def keep_evaluator_params(version: str | None = None) -> Iterator[EvaluatorHook]:
    """For the block, ``brax.training.acting.Evaluator`` is a subclass whose ``run_evaluation(policy_params,
    training_metrics, ...)`` keeps ``policy_params`` in the yielded :class:`EvaluatorHook` and returns the training
    metrics without running Brax's evaluation rollout. The original class is back after the block, whether it
    ends normally or raises. ``version`` (default: the installed Brax) exists so the guard can be tested."""
    from brax.training import acting

    version = installed_version() if version is None else version
    original = acting.Evaluator
    run = getattr(original, "run_evaluation", None)
    if not isinstance(original, type) or not callable(run):
        raise BraxCompatError(f"brax {version}: brax.training.acting.Evaluator has no run_evaluation method, which "
                              f"jaxrobo's SAC evaluation replaces (written for brax {_range()})")
    reason = unavailable(version)
    if reason is not None:
        warn_once(_WARNED, f"jaxrobo.interop.brax_compat: {reason}; swapping brax.training.acting.Evaluator for "
                  "SAC's evaluation points anyway, untested with this Brax")
    hook = EvaluatorHook(version)

    class KeepParams(original):  # type: ignore[misc, valid-type]
        def run_evaluation(self, policy_params, training_metrics, aggregate_episodes=True):
            hook.keep(policy_params)
            return dict(training_metrics)

    acting.Evaluator = KeepParams
    try:
        yield hook
    finally:
        acting.Evaluator = original


@dataclasses.dataclass
class EpochHook:
    """What :func:`hook_epochs` yields. ``epochs_done`` counts the trainer's epochs over the whole run (it starts
    at ``first_epoch``); ``states`` is the tuple of state pytrees the last epoch returned (PPO: training state,
    env state; SAC: and the replay buffer), device arrays with Brax's leading device axis, valid until the next
    epoch starts (Brax donates them to it)."""

    version: str | None
    epoch_keys: Callable[[int, int], Any]
    epochs_done: int = 0
    states: Any = None
    calls: int = 0
    _restore: Callable[[tuple], tuple] | None = None
    #: ``compile_epoch(mapped, args, donate) -> callable or None``: the program the epochs run instead of the
    #: mapped epoch itself (asked once, with the first epoch's arguments; None: the mapped epoch).
    compile_epoch: Callable[[Callable, tuple, tuple], Callable | None] | None = None

    def wrap(self, epoch_fn: Callable, axis_name: Any = None, donate: tuple = ()) -> Callable:
        compiled: list[Callable] = []

        def run(*args: Any) -> Any:
            *states, key = args
            if self._restore is not None:
                states, self._restore = list(self._restore(tuple(states))), None
            states = _as_mapped(states, axis_name)
            ours = self.epoch_keys(self.epochs_done, key.shape[0])
            if ours.shape != key.shape or ours.dtype != key.dtype:
                raise BraxCompatError(f"brax {self.version}: training_epoch's key is {key.dtype}{list(key.shape)}, "
                                      f"jaxrobo's epoch key {ours.dtype}{list(ours.shape)} (written for brax "
                                      f"{_range()})")
            if not compiled:
                made = None if self.compile_epoch is None else self.compile_epoch(epoch_fn, (*states, ours), donate)
                compiled.append(made if made is not None else epoch_fn)
            fn = compiled[0]
            if fn is not epoch_fn:  # a compiled program takes its arguments on the shardings it was compiled for
                states = list(jax.device_put(tuple(states), tuple(fn.input_shardings[0][:-1])))
            out = fn(*states, ours)
            self.states, self.epochs_done, self.calls = tuple(out[:-1]), self.epochs_done + 1, self.calls + 1
            return out

        return run

    def check(self) -> None:
        """Raise :class:`BraxCompatError` if no epoch ran through the hook (a Brax whose trainer no longer builds
        its epoch with ``jax.pmap`` of a function named ``training_epoch``)."""
        if self.calls == 0:
            raise BraxCompatError(f"brax {self.version}: the trainer ran no jax.pmap-ed training_epoch, so its state "
                                  f"could not be kept; jaxrobo.interop.brax_compat was written for brax {_range()}")


class _JaxWithEpochHook:
    """The ``jax`` module, except that ``pmap`` of a function named ``training_epoch`` goes through the hook."""

    def __init__(self, hook: EpochHook):
        self._hook = hook

    def __getattr__(self, name: str) -> Any:
        return getattr(jax, name)

    def pmap(self, fun: Callable, *args: Any, **kwargs: Any) -> Any:
        mapped = jax.pmap(fun, *args, **kwargs)
        if getattr(fun, "__name__", None) != "training_epoch":
            return mapped
        donate = kwargs.get("donate_argnums", ())
        donate = (donate,) if isinstance(donate, int) else tuple(donate)
        return self._hook.wrap(mapped, kwargs.get("axis_name"), donate)


def _as_mapped(states: list, axis_name: Any) -> list:
    """``states`` with every leaf on the sharding the mapped epoch gives its outputs (a mesh of the leaves' devices
    along ``axis_name``), so that the first epoch's arguments match every later epoch's and the epoch is lowered
    and compiled once, not twice: the trainer's first state comes from ``device_put_replicated`` (another mesh's
    axis name), and the jit cache keys on the arguments' shardings. A leaf already there is not moved."""
    if axis_name is None:
        return states
    targets: dict[tuple, Any] = {}

    def put(leaf: Any) -> Any:
        sharding = getattr(leaf, "sharding", None)
        if not isinstance(sharding, jax.sharding.NamedSharding) or sharding.mesh.axis_names == (axis_name,):
            return leaf
        devices = tuple(sharding.mesh.devices.flat)
        if devices not in targets:
            mesh = jax.sharding.Mesh(np.asarray(devices), (axis_name,))
            targets[devices] = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(axis_name))
        return jax.device_put(leaf, targets[devices])

    return jax.tree.map(put, states)


@contextlib.contextmanager
def hook_epochs(trainer_module: Any, epoch_keys: Callable[[int, int], Any], first_epoch: int = 0,
                restore: Callable[[tuple], tuple] | None = None, version: str | None = None,
                compile_epoch: Callable[[Callable, tuple, tuple], Callable | None] | None = None
                ) -> Iterator[EpochHook]:
    """For the block, the trainer module's epochs run through the yielded :class:`EpochHook` (see the module
    docstring): ``epoch_keys(i, n_devices)`` (raw ``uint32[n_devices, 2]`` keys, as Brax's own) are the keys of the
    run's ``i``-th epoch, counting from ``first_epoch``; ``restore(fresh_states) -> states``, if given, replaces
    the state tuple at the first epoch. ``compile_epoch(mapped, args, donate)``, if given, is asked once, with the
    first epoch's arguments and the mapped epoch's donated positions, for the program every epoch then runs (a
    compiled one: its arguments are put on its input shardings), or None to run the mapped epoch (see
    :func:`jaxrobo.deep.training.train`: a kept trace of it). ``version`` (default: the installed Brax) exists so
    the guard can be tested."""
    version = installed_version() if version is None else version
    if getattr(trainer_module, "jax", None) is not jax:
        raise BraxCompatError(f"brax {version}: {getattr(trainer_module, '__name__', trainer_module)} does not use "
                              f"the jax module by that name, which jaxrobo's epoch hook replaces (written for brax "
                              f"{_range()})")
    reason = unavailable(version)
    if reason is not None:
        warn_once(_WARNED, f"jaxrobo.interop.brax_compat: {reason}; hooking {trainer_module.__name__}'s "
                  "training_epoch anyway, untested with this Brax")
    hook = EpochHook(version, epoch_keys, epochs_done=first_epoch, _restore=restore, compile_epoch=compile_epoch)
    trainer_module.jax = _JaxWithEpochHook(hook)
    try:
        yield hook
    finally:
        trainer_module.jax = jax


#: How each trainer's ``training_epoch`` moves its key on at every training step (the carry of its ``lax.scan``):
#: PPO's ``training_step`` splits the key in three and carries the third; SAC's epoch splits it in two and
#: carries the second.
_CARRIED = {"ppo": (3, 2), "sac": (2, 1)}


# ``steps`` is traced: an epoch run as many host iterations asks for a different count at each (one compile for all)
@functools.partial(jax.jit, static_argnums=(1, 2))
def _advance(keys: Any, parts: int, index: int, steps: Any) -> Any:
    def one(key: Any) -> Any:
        return jax.lax.fori_loop(0, steps, lambda _, k: jax.random.split(k, parts)[index], key)

    return jax.vmap(one)(keys)


def advance_epoch_keys(agent: str, keys: Any, steps: int) -> Any:
    """The keys (one per device, raw ``uint32[2]``) that ``agent``'s (``ppo`` or ``sac``) ``training_epoch``
    carries after ``steps`` of its training steps when it starts from ``keys``: an epoch of ``n`` steps equals an
    epoch of ``steps`` followed by one of ``n - steps`` that starts from these keys, bit for bit
    (``tests/test_brax_compat.py`` checks it on the installed Brax)."""
    if steps == 0:
        return keys
    parts, index = _CARRIED[agent]
    return _advance(keys, parts, index, int(steps))
