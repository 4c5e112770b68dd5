"""Memory a training batch needs, estimated from its shapes before anything compiles, against what is available.

A run's big arrays are known from its config alone: the Q-tables (``n_envs x n_tables x n_states x n_actions``
float32, one set when ``shared_table``), the episode records (``n_envs x nepisodes`` of return float32, length
int32 and terminated bool: 9 bytes) and the env states. :func:`check_memory` refuses a batch whose estimate does
not fit, with the figure and the limit, instead of letting XLA fail (or the machine swap) after a compile.

The limit is the device's free memory (``memory_stats()``: ``bytes_limit - bytes_in_use``) where the backend
reports it, else the host's available RAM (a CPU device's arrays live there).
"""
from __future__ import annotations

import math
from typing import Any

from jaxrobo.core.config import ConfigError

#: Bytes of one episode record: return (float32) + length (int32) + terminated (bool).
RECORD_BYTES = 4 + 4 + 1
#: A generous bound on one env's state and its step temporaries: the largest shipped task's state is a few
#: hundred bytes, so batches that fit with this much per env skip tracing ``env.reset`` for the exact figure.
ENV_BOUND_BYTES = 1 << 20
#: Env states are held several times over in a step (the state, the stepped state, fresh resets, temporaries).
ENV_COPIES = 4


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def host_available_bytes() -> int | None:
    """Available host RAM (``MemAvailable`` of /proc/meminfo, else psutil), or None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001 - unknown is allowed: no check then
        return None


def available_bytes() -> tuple[int | None, str]:
    """``(bytes, what)``: free memory of the default device, or the host's available RAM on a CPU."""
    import jax

    dev = jax.devices()[0]
    if dev.platform != "cpu":
        try:
            stats = dev.memory_stats() or {}
        except Exception:  # noqa: BLE001 - not every backend reports
            stats = {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)), f"free memory of {dev.device_kind}"
    return host_available_bytes(), "available host RAM"


def tables_bytes(n_envs: int, n_tables: int, n_states: int, n_actions: int, shared_table: bool = False) -> int:
    return (1 if shared_table else n_envs) * n_tables * n_states * n_actions * 4


def records_bytes(n_envs: int, nepisodes: int, record_episodes: bool = True) -> int:
    return n_envs * (nepisodes if record_episodes else 1) * RECORD_BYTES


def env_state_bytes(env: Any) -> int:
    """One env's state in bytes, from the shapes of ``env.reset`` (traced abstractly: nothing compiles or runs)."""
    import jax

    from jaxrobo.task.env import reset_shapes

    state = reset_shapes(env)
    total = 0
    for leaf in jax.tree.leaves(state):
        dtype = getattr(leaf, "dtype", None)
        if dtype is None:
            continue
        itemsize = 8 if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) else dtype.itemsize
        total += math.prod(leaf.shape) * itemsize
    return total


def estimate(env: Any, config: Any, n_states: int, exact_env: bool = False) -> dict[str, int]:
    """Bytes per part of a training batch: ``tables``, ``records``, ``envs`` (and their ``total``).

    ``envs`` uses :data:`ENV_BOUND_BYTES` per env unless ``exact_env``, then the traced state size.
    On a CPU the tables and records are counted twice: the result is copied to host memory, the same RAM.
    """
    from jaxrobo.task.registry import learner

    n_tables = learner(config.agent).n_tables
    per_env = ENV_COPIES * env_state_bytes(env) if exact_env else ENV_BOUND_BYTES
    parts = {
        "tables": tables_bytes(config.n_envs, n_tables, n_states, env.num_actions, config.shared_table),
        "records": records_bytes(config.n_envs, config.nepisodes, config.record_episodes),
        "envs": config.n_envs * per_env,
    }
    if _default_platform() == "cpu":
        parts["tables"] *= 2
        parts["records"] *= 2
    parts["total"] = sum(parts.values())
    return parts


def _default_platform() -> str:
    import jax

    return jax.default_backend()


def check_memory(env: Any, config: Any, n_states: int, limit: int | None = None, what: str | None = None,
                 where: str = "") -> dict:
    """Refuse (ConfigError with the figure and the limit) a batch whose estimate exceeds the available memory.

    ``limit`` defaults to :func:`available_bytes`. Returns the estimate. The exact env-state size is traced only
    when the generous per-env bound does not already fit (and not at all when tables and records alone do not).
    """
    if limit is None:
        limit, what = available_bytes()
    if limit is None:
        return {}
    what = what or "the limit"
    parts = estimate(env, config, n_states)
    base = parts["tables"] + parts["records"]
    if base <= limit < parts["total"]:
        parts = estimate(env, config, n_states, exact_env=True)
    if base > limit or parts["total"] > limit:
        if base > limit:  # the env states are not even needed to refuse: leave out their (bounded) guess
            parts = {"tables": parts["tables"], "records": parts["records"], "total": base}
        detail = ", ".join(f"{k} {format_bytes(v)}" for k, v in parts.items() if k != "total")
        loc = f"{where}: " if where else ""
        raise ConfigError(
            f"{loc}n_envs={config.n_envs}: the batch needs {'at least' if base > limit else 'about'} "
            f"{format_bytes(parts['total'])} ({detail}; {n_states:,} states x {env.num_actions} actions per table, "
            f"nepisodes={config.nepisodes} recorded) but {what} is {format_bytes(limit)}; use fewer n_envs, "
            f"nepisodes or bins (or shared_table=true, record_episodes=false)")
    return parts


#: Bytes per step of one evaluation episode kept by the rollout (reward, alive, action, return and length
#: temporaries): a bound, so that a huge ``eval_episodes`` is refused before the compile rather than by XLA.
EVAL_STEP_BYTES = 16


def eval_bytes(env: Any, n_tables: int, n_episodes: int, horizon: int, exact_env: bool = False) -> int:
    """Bytes of a greedy evaluation of ``n_tables`` tables x ``n_episodes`` episodes at once, ``horizon`` steps
    each (:meth:`jaxrobo.training.trainer.Trainer.evaluate_episodes` vmapped over tables)."""
    per_env = ENV_COPIES * env_state_bytes(env) if exact_env else ENV_BOUND_BYTES
    return n_tables * n_episodes * (per_env + horizon * EVAL_STEP_BYTES)


def check_eval_memory(env: Any, n_tables: int, n_episodes: int, horizon: int, where: str = "",
                      limit: int | None = None, what: str | None = None) -> int:
    """Refuse (ConfigError with the estimate and the limit) an evaluation that would not fit; returns the
    estimate (0 when there is no evaluation or no known limit). The exact env-state size is traced only when
    the generous bound does not fit."""
    if n_episodes <= 0 or n_tables <= 0:
        return 0
    if limit is None:
        limit, what = available_bytes()
    if limit is None:
        return 0
    need = eval_bytes(env, n_tables, n_episodes, horizon)
    if need > limit:
        need = eval_bytes(env, n_tables, n_episodes, horizon, exact_env=True)
    if need > limit:
        loc = f"{where}: " if where else ""
        raise ConfigError(f"{loc}eval_episodes={n_episodes}: the greedy evaluation of {n_tables} table(s) x "
                          f"{n_episodes:,} episodes of up to {horizon} steps needs about {format_bytes(need)} but "
                          f"{what or 'the limit'} is {format_bytes(limit)}; evaluate fewer episodes")
    return need


#: A bound on the host memory one sweep row takes while it is planned (its point, its validated values, its
#: learner and env parameters, its metrics): rows are Python objects before they are stacked into arrays.
SWEEP_ROW_HOST_BYTES = 16 << 10


def check_sweep_rows(n_configs: int, n_seeds: int, where: str = "", limit: int | None = None) -> int:
    """Refuse (ConfigError with the estimate and the limit) a sweep of more rows (configurations x seeds) than
    the host can plan, before a single row is built; returns the number of rows."""
    rows = n_configs * n_seeds
    if limit is None:
        limit = host_available_bytes()
    need = rows * SWEEP_ROW_HOST_BYTES
    if limit is not None and need > limit:
        loc = f"{where}: " if where else ""
        raise ConfigError(f"{loc}{n_configs:,} configurations x {n_seeds:,} seeds = {rows:,} rows: planning them "
                          f"needs about {format_bytes(need)} of host memory but available host RAM is "
                          f"{format_bytes(limit)}; sweep fewer points or seeds")
    return rows
