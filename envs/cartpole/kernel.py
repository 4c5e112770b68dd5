"""The cart-pole with Q-learning, a whole training chunk as one Pallas kernel (``ExecutionPlan(fused="pallas")``).

The plain path runs a training step as ~20-30 batch-wide kernels, each reading and writing part of every env's
state. Here one ``pallas_call`` runs the whole chunk: each program takes a block of envs and loops over the
chunk's steps in-kernel, the env's state, keys, epsilon, counters and its current table row in registers; per
step it touches memory only to gather the next state's table row and scatter the one updated entry (the env's
own table, by computed index), to record a finished episode, and to gather the fresh state's row after a reset.
The carry goes back to memory once, at the end of the chunk. A program is one warp of 32 envs by default
(:data:`BLOCK`). Three choices of the :class:`~jaxrobo.speed.plan.ExecutionPlan` (``skip_resets``,
``group_resets``, ``fast_sincos``) take integer and logic instructions out of a kernel bound by their issue; each
keeps every value (docs/benchmarks.md, "Pallas").

A step is six phases, each a method of :class:`_Program` (one program's view of the kernel): :meth:`~_Program.act`
(keys, the run's budget, epsilon-greedy, the task's action map), :meth:`~_Program.env_step` (the physics, the NaN
guard, the task's outcome and reward, observation noise), :meth:`~_Program.learn` (discretise, Q-learning's update
of the carried rows), :meth:`~_Program.record` (the finished episodes), :meth:`~_Program.reset` (the fresh
episodes) and :meth:`~_Program.write_back` (the table entry and the carry).

It is :meth:`jaxrobo.training.trainer.Trainer.step` written out for one case, in the same arithmetic order, with the
same random numbers: the keys are JAX's threefry keys and the kernel hashes them with :mod:`jaxrobo.core.rng`'s own
hash (:func:`~jaxrobo.core.rng.threefry2x32`, :func:`~jaxrobo.core.rng.unit_float`; JAX's partitionable layout), so
the draws are ``jax.random``'s own. What it shares with the task and what it cannot:

* the physics is the simulator's own, :meth:`CartPoleSim.coordinate_step
  <envs.cartpole.dynamics.CartPoleSim.coordinate_step>` on ``[block]`` vectors of the four coordinates (the Triton
  lowering has no slice, so the kernel cannot take the stacked form the env's step runs), with, on a GPU,
  libdevice's ``sin``/``cos`` written out where the plan's ``fast_sincos`` and the GPU allow;
* the command and the outcome are the task's own per-coordinate rules (:func:`envs.cartpole.rules.command_after`,
  :func:`envs.cartpole.rules.fell`), which its hooks call too; the action's step is a select chain over
  :data:`envs.cartpole.rules.ACTION_STEPS` (a kernel has no gather from a constant array);
* the rest is written here because a Pallas kernel cannot run the XLA forms: parameters are scalars read once from a
  parameter vector (no pytree of params), a table row is ``n_actions`` scalars gathered by computed index (no
  ``q[s]``), the action's table entry is a select chain (no dynamic index into a row), and a key is its two
  uint32 words apart, split and folded by hashing them directly (no key arrays in a kernel). The reward (1 each
  step, 0 where the NaN guard fires) is :meth:`jaxrobo.task.env.TaskEnv.step`'s guard on the task's constant
  reward.

On a CPU (``interpret=True``, what the tests run) keys, actions, updates, resets and records follow the plain path
bit for bit while the physics state agrees to its last bits: op by op the two forms give the same bits, but XLA
fuses the kernel's program and the env's step differently and contracts a multiply and an add that share a fusion
into one FMA, which rounds once instead of twice. Once such a bit moves a state across a bin edge the runs part
ways, as any last-bit change does in tabular learning; on a GPU Triton compiles ``sin``/``cos`` and the
multiply-adds, so the same holds there. Learning results stay within the seed-to-seed spread.

Domain randomisation (the task's ``randomise``, :mod:`jaxrobo.task.randomise`): the kernel resets envs in-kernel,
so it draws each fresh episode's cart mass, pole mass, pole length and observation noise there, from the keys
``randomise.draw`` folds out of the reset key (the bounds are traced parameters in the kernel's parameter
vector), carries them as per-env columns into ``coordinate_step`` (``physics=``, the XLA step's own
:func:`envs.cartpole.dynamics.randomised`), and adds the observation noise from the keys ``randomise.noisy``
folds out of the env key (JAX's normal draw: a uniform per component, then ``sqrt(2) erfinv``, the latter as
:func:`_erf_inv`, JAX's values with fewer registers; the episode's noise key, the env key folded with the noise
tag, is carried): fifteen more hashes per reset (nine for the draws, six for the first observation's noise) and
five per step; a program whose fresh episodes, or whose envs, all drew a noise level of 0 skips the noise's (one
scalar branch each). Under ``group_resets`` the groups are of eight lanes and hash the draws too. Off, the kernel
has none of these columns: the program it was.

Supported (:func:`unsupported_run` says why not): ``CartPoleStayUp`` on the ``analytic`` backend with
``control_type="velocity"`` and ``round_obs`` off, randomised or not; Q-learning, textbook form (not
``seed_compat``), one table per env (not ``shared_table``); the ``bins`` or ``round`` discretiser; threefry keys
with ``jax_threefry_partitionable`` (JAX's default). A sweep vmaps the chunk over its configurations: Pallas
batches the call.

How it is used: the task offers :data:`CHUNK_KERNEL` as its ``chunk_kernel``
(:attr:`jaxrobo.task.env.TaskEnv.chunk_kernel`); :mod:`jaxrobo.speed.plan` asks it which runs it takes and the
trainer runs it. Public surface: :data:`CHUNK_KERNEL`, :func:`unsupported_run`, :func:`run_chunk`, :data:`BLOCK`.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.cartpole.dynamics import CartPoleSim
from envs.cartpole.rules import command_after, fell
from jaxrobo.api import AgentState, EnvState, JointState, randomise, rng

#: Envs per Pallas program when the plan's ``fused_block`` is None (a power of two; smaller where ``n_envs`` has
#: fewer factors of two), one per GPU thread (``num_warps`` is ``block / 32``, 1 to 8).
#: ``ExecutionPlan(fused="pallas", fused_block=B)`` asks for B (a power of two up to 1024).
BLOCK = 32
_MAX_BLOCK = 1024

# The float parameters, in the order of the kernel's parameter vector.
_F = ("pos_step", "max_base_velocity", "min_pole_angle", "max_pole_angle", "min_base_pose_x", "max_base_pose_x",
      "init_pos", "init_pole_angle", "init_noise", "alpha", "gamma", "epsilon_discount", "epsilon_min",
      "low0", "low1", "low2", "low3", "width0", "width1", "width2", "width3")
_PARAMS = 32
#: What a randomised run's kernel draws per env at every reset (domain randomisation: the cart-pole's ranges,
#: :mod:`jaxrobo.task.randomise`), carried as per-env columns of these names beside the state.
_DOMAIN = ("cart_mass", "pole_mass", "pole_length", randomise.OBS_NOISE)
#: The task's hooks whose meaning the kernel holds: a subclass overriding one of them gets no kernel.
HOOKS = ("step", "reset", "_set_init_pose", "_init_env_variables", "_set_action", "_get_obs", "_is_done",
         "_compute_reward")
#: ``jax.random.normal``'s float32 interval: its uniform draws lie in ``[nextafter(-1, 0), 1)``.
_NORMAL_LOW = np.nextafter(np.float32(-1.0), np.float32(0.0))
_NORMAL_SPAN = np.float32(1.0) - _NORMAL_LOW


def unsupported_run(env: Any, config: Any, agent: str, discretiser: Any, fused_block: int | None = None) -> str | None:
    """Why training ``env`` (a task offering this kernel) with ``config`` (a
    :class:`jaxrobo.training.trainer.TrainConfig`) cannot take the kernel (None: it can); the one place its rules
    live, read both by the plan's default and by the boundary that refuses an explicit choice
    (:func:`jaxrobo.speed.plan.chunk_kernel_refusal`). ``agent``: the learner's name; ``discretiser``: the run's
    :class:`jaxrobo.tabular.discretise.Discretiser`; ``fused_block``: the plan's envs per program."""
    c = config
    o = env.options
    # A subclass that overrides a hook whose meaning the kernel holds gets no kernel (its meaning would be lost).
    owner = next(cls for cls in type(env).__mro__ if "chunk_kernel" in cls.__dict__)
    changed = [h for cls in type(env).__mro__[:type(env).__mro__.index(owner)] for h in HOOKS if h in cls.__dict__]
    if changed:
        return f"{type(env).__name__} overrides {', '.join(changed)}, whose meaning the kernel holds"
    if not isinstance(env.robot.sim, CartPoleSim):
        return f"backend={o.backend!r}; only backend='analytic'"
    if getattr(o, "randomise", False):
        names = randomise.range_fields(type(env.default_params))
        other = [n for n in names if n not in _DOMAIN]
        if other or env.robot.directional:
            return (f"randomise=true with the ranges {', '.join(randomise.PREFIX + n for n in other)}; the kernel "
                    f"draws only {', '.join(randomise.PREFIX + n for n in _DOMAIN)}")
    if o.control_type != "velocity" or o.round_obs:
        return (f"control_type={o.control_type!r}, round_obs={o.round_obs}; "
                "only control_type='velocity' without round_obs")
    if agent != "qlearn" or c.seed_compat or c.shared_table:
        return f"agent={agent!r} (seed_compat={c.seed_compat}, shared_table={c.shared_table}); " \
               "only agent='qlearn' with per-env tables, not seed_compat"
    if discretiser.edges is not None:
        return "discretiser='edges'; only 'bins' or 'round'"
    if not jax.config.jax_threefry_partitionable or jax.config.jax_default_prng_impl != "threefry2x32":
        return "only JAX's default threefry keys with jax_threefry_partitionable"
    b = fused_block
    if b is not None and (b > _MAX_BLOCK or b & (b - 1)):
        return f"fused_block={b}; with fused='pallas' the envs per program, a power of two up to {_MAX_BLOCK}"
    if c.n_envs * discretiser.n_states * env.num_actions >= 2**31:
        return "the tables hold 2**31 entries or more (int32 indices)"
    if getattr(c, "total_episodes", 0):
        return ("total_episodes: a run-wide episode count needs every env's episodes at every step, which one "
                "program of the kernel does not see; only the per-env episode budget or total_steps")
    if c.record_episodes and c.n_envs * c.nepisodes >= 2**31:
        return "the episode records hold 2**31 entries or more (int32 indices); set record_episodes=False"
    return None


# ---- in-kernel random numbers: jaxrobo.core.rng's hash on [block] uint32 vectors, a key's two words apart --------
def _subkey(key, index):
    """``split(key, num)[index]`` (any ``num``): the hash of counter ``(0, index)``."""
    zero = jnp.zeros_like(key[0])
    return rng.threefry2x32(key[0], key[1], zero, zero + jnp.uint32(index))


def _any(mask):
    """Whether any lane of the program is set: an integer maximum, one warp-wide reduction on a GPU."""
    return jnp.max(mask.astype(jnp.int32)) > 0


# XLA's float32 ErfInv (JAX's own lowering of it in Pallas, pallas.utils._erf_inv_32_lowering_helper): one polynomial
# in w - 2.5 where w = -log1p(-x^2) < 5, another in sqrt(w) - 3 elsewhere.
_ERFINV_BELOW_5 = (2.81022636e-08, 3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087, -0.00125372503,
                   -0.00417768164, 0.246640727, 1.50140941)
_ERFINV_ABOVE_5 = (-0.000200214257, 0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773, -0.0076224613,
                   0.00943887047, 1.00167406, 2.83297682)


def _erf_inv(x):
    """``jax.lax.erf_inv`` as its lowering computes it, each branch's polynomial evaluated with its own constants and
    the result selected, rather than each coefficient selected ahead of one polynomial: the same operations on each
    lane's branch, with the constants in the instructions instead of nine selected registers per value."""
    w = -jnp.log1p(x * -x)

    def horner(constants, t):
        p = jnp.full_like(t, constants[0])
        for c in constants[1:]:
            p = c + p * t
        return p

    p = jnp.where(w < 5.0, horner(_ERFINV_BELOW_5, w - 2.5), horner(_ERFINV_ABOVE_5, jnp.sqrt(w) - 3.0))
    return jnp.where(jnp.abs(x) == 1.0, jnp.inf * x, p * x)


def _row_max(r):
    return functools.reduce(jnp.maximum, r)


def _epsilon_greedy(key, r, epsilon, n_actions):
    x1, x2 = rng.threefry2x32(key[0], key[1], jnp.zeros_like(key[0]), jnp.zeros_like(key[0]))
    coin, u = rng.unit_float(x1), rng.unit_float(x2)
    random_action = jnp.minimum(jnp.floor(u * n_actions), n_actions - 1).astype(jnp.int32)
    best = _row_max(r)
    is_max = [ri == best for ri in r]
    count = is_max[0].astype(jnp.int32)
    for m in is_max[1:]:
        count = count + m.astype(jnp.int32)
    wanted = jnp.minimum(jnp.floor(u * count.astype(jnp.float32)).astype(jnp.int32), count - 1)
    choice, seen = jnp.zeros_like(count), jnp.zeros_like(count)
    for i, m in enumerate(is_max):
        choice = jnp.where(m & (seen == wanted), jnp.int32(i), choice)
        seen = seen + m.astype(jnp.int32)
    return jnp.where(coin < epsilon, random_action, choice)


def _drawn_from(key_i, low, high):
    # One range's value from its key: one uniform (counter (0, 0), the two words xor-ed) scaled to
    # [low, high).
    zero = jnp.zeros_like(key_i[0])
    u = rng.unit_float(functools.reduce(jnp.bitwise_xor, rng.threefry2x32(key_i[0], key_i[1], zero, zero)))
    return low + u * (high - low)


def _draw(base, fold, low, high):
    # One range's value: its key folded out of the draws' base key (the hash of counter (0, fold), fold
    # = 2 i for range i), then drawn_from that key.
    zero = jnp.zeros_like(base[0])
    return _drawn_from(rng.threefry2x32(base[0], base[1], zero, zero + fold), low, high)


def _noisy(obs, episode_key, steps, std):
    # randomise.noisy: obs + std * jax.random.normal(fold_in(fold_in(env_key, tag), steps), (4,)), the
    # normal draw as JAX's: a uniform in [nextafter(-1, 0), 1) per component (counter (0, j)), then
    # sqrt(2) erfinv. ``episode_key``: fold_in(env_key, tag), carried per episode.
    zero = jnp.zeros_like(episode_key[0])
    step_key = rng.threefry2x32(episode_key[0], episode_key[1], zero, steps.astype(jnp.uint32))
    out = []
    for j, o in enumerate(obs):
        bits = functools.reduce(jnp.bitwise_xor, rng.threefry2x32(step_key[0], step_key[1], zero, zero + jnp.uint32(j)))
        u = jnp.maximum(jnp.float32(_NORMAL_LOW), rng.unit_float(bits) * jnp.float32(_NORMAL_SPAN)
                        + jnp.float32(_NORMAL_LOW))
        out.append(o + std * (jnp.float32(np.sqrt(2)) * _erf_inv(u)))
    return tuple(out)


def _finite(v):
    return jnp.abs(v) < jnp.inf


# ---- the kernel --------------------------------------------------------------------------------------------
_COLS = (  # per-env carry columns: name, dtype
    ("x", jnp.float32), ("th", jnp.float32), ("xd", jnp.float32), ("thd", jnp.float32),
    ("o0", jnp.float32), ("o1", jnp.float32), ("o2", jnp.float32), ("o3", jnp.float32),
    ("reward", jnp.float32), ("term", jnp.int32), ("trunc", jnp.int32), ("steps", jnp.int32),
    ("command", jnp.float32), ("ek0", jnp.uint32), ("ek1", jnp.uint32), ("pnan", jnp.int32),
    ("s", jnp.int32), ("r0", jnp.float32), ("r1", jnp.float32), ("r2", jnp.float32), ("r3", jnp.float32),
    ("action", jnp.int32), ("epsilon", jnp.float32), ("episode", jnp.int32), ("ep_return", jnp.float32),
    ("k0", jnp.uint32), ("k1", jnp.uint32), ("nan_episodes", jnp.int32), ("env_steps", jnp.int32),
    ("ret_sum", jnp.float32), ("len_sum", jnp.int32), ("term_any", jnp.int32))


def _columns(domain: tuple[str, ...]) -> tuple:
    """The carry's columns: :data:`_COLS`, and under domain randomisation one float column per drawn quantity and,
    with observation noise, the episode's noise key (the env key folded with the noise tag: one hash per step
    fewer than folding it every step; an input only, the env state keeps the env key)."""
    noise = ((("nk0", jnp.uint32), ("nk1", jnp.uint32)) if randomise.OBS_NOISE in domain else ())
    return _COLS + tuple((name, jnp.float32) for name in domain) + noise


def _float_names(domain: tuple[str, ...]) -> tuple[str, ...]:
    """The kernel's float parameters: :data:`_F`, and under domain randomisation each range's two bounds."""
    return _F + tuple(f"rand_{bound}{i}" for i in range(len(domain)) for bound in ("low", "high"))


@dataclasses.dataclass(frozen=True)
class _Static:
    """What a kernel is specialised for (host values, baked into the program)."""

    block: int
    steps_per_chunk: int
    n_states: int
    n_actions: int
    n_rec: int
    records: bool
    nepisodes: int
    nsteps: int
    strides: tuple[int, ...]
    bins: tuple[int, ...]
    coordinate_step: Callable
    n_substeps: int
    action_steps: tuple[float, ...]  # the task's command step per action
    skip_resets: bool
    group_resets: bool
    written: Any  # the written-out sin/cos (.sincos, .limit) under the plan's fast_sincos; None: the calls
    steps_budget: int  # steps per env under total_steps, else 0 (episodes per env)
    domain: tuple[str, ...]  # drawn quantities in the order of the task's ranges; empty: not randomised

    @property
    def noise_on(self) -> bool:
        return randomise.OBS_NOISE in self.domain

    @property
    def group_lanes(self) -> int:
        """Lanes per group that hash a done env's reset (``group_resets``): four, under domain randomisation eight
        (slots 0-3 the pose, 4 + i range i)."""
        return 8 if self.domain else 4


def _physics_names() -> tuple[str, ...]:
    return tuple(n for n in _DOMAIN if n != randomise.OBS_NOISE)


def _make_kernel(st: _Static) -> Callable:
    assert len(st.domain) <= 4, st.domain
    columns = _columns(st.domain)
    names = tuple(name for name, _ in columns)
    n_cols = len(columns)

    def kernel(fp_ref, ip_ref, *refs):
        ins = refs[:n_cols]
        rest = refs[n_cols:]
        n_big = 4 if st.records else 1
        outs = rest[n_big:n_big + n_cols]
        q_ref = rest[n_big + n_cols]
        rec_refs = rest[n_big + n_cols + 1:n_big + n_cols + 4] if st.records else None
        program = _Program(st, fp_ref, ip_ref, dict(zip(names, ins)), q_ref, rec_refs)
        carry = jax.lax.fori_loop(0, st.steps_per_chunk, lambda _, cr: program.step(cr), program.carry)
        for name, ref in zip(names, outs):
            ref[...] = carry[name].astype(ref.dtype)

    return kernel


class _Program:
    """One Pallas program's view of the kernel: its envs, the parameters (read once, kept in registers) and the
    tables; :meth:`step` is one training step of its envs as the five phases."""

    def __init__(self, st: _Static, fp_ref: Any, ip_ref: Any, ins: dict, q_ref: Any, rec_refs: Any):
        from jax.experimental import pallas as pl

        self.st, self.q_ref, self.rec_refs = st, q_ref, rec_refs
        fvals = {name: fp_ref[i] for i, name in enumerate(_float_names(st.domain))}
        self.f = fvals.__getitem__
        self.max_episode_steps = ip_ref[0]
        env0 = pl.program_id(0) * st.block
        self.env = env0 + jax.lax.iota(jnp.int32, st.block)
        self.carry = {name: ref[...] for name, ref in ins.items()}  # the chunk's first carry
        self.base = self.env * (st.n_states * st.n_actions)  # [env, state, action]

    # ---- the tables and the discretiser --------------------------------------------------------------------
    def row_at(self, s):
        return self.base + s * self.st.n_actions

    def row(self, s, mask=None):
        from jax.experimental.pallas import triton as plgpu

        at = self.row_at(s)
        return [plgpu.load(self.q_ref.at[at + k], mask=mask, other=0.0 if mask is not None else None)
                for k in range(self.st.n_actions)]

    def discretise(self, o):
        st, f = self.st, self.f
        idx = []
        for d in range(4):
            i = jnp.floor((o[d] - f(f"low{d}")) / f(f"width{d}")).astype(jnp.int32)
            idx.append(jnp.minimum(jnp.maximum(i, 0), st.bins[d] - 1))
        total = idx[0] * st.strides[0]
        for d in range(1, 4):
            total = total + idx[d] * st.strides[d]
        return total

    # ---- random numbers of the task's randomisation ----------------------------------------------------------
    def draws(self, k_reset):
        """randomise.draw(k_reset, params): one uniform per range from the reset key folded with the draw tag
        (fold_in is the hash of counter (0, data), as _subkey), each from its own fold, in range order."""
        f = self.f
        base = _subkey(k_reset, randomise.DRAW_TAG)
        return [_draw(base, jnp.uint32(2 * i), f(f"rand_low{i}"), f(f"rand_high{i}"))
                for i in range(len(self.st.domain))]

    def noise_of(self, w1, w2):
        """The reset's uniform noise in ``±init_noise`` from one hash's two words."""
        lo = -self.f("init_noise")
        return rng.unit_float(w1 ^ w2) * (self.f("init_noise") - lo) + lo

    # ---- the reset's random numbers ----------------------------------------------------------------------
    def hashed_by_lane(self, key):
        f = self.f
        # Every lane hashes its own env's seven: the reset key, the env key and the pose key from it,
        # and the pose's four uniforms.
        k_reset = _subkey(key, 4)
        rk, pose_key = _subkey(k_reset, 0), _subkey(k_reset, 1)
        zero = jnp.zeros_like(pose_key[0])
        noise = [self.noise_of(*rng.threefry2x32(pose_key[0], pose_key[1], zero, zero + jnp.uint32(j)))
                 for j in range(4)]
        return (f("init_pos") + noise[0], f("init_pole_angle") + noise[2], noise[1], noise[3], *rk,
                *self.draws(k_reset))

    def hashed_by_group(self, key, done, n_done):
        f, st = self.f, self.st
        block, group_lanes, domain = st.block, st.group_lanes, st.domain
        # The same seven hashes of each done env, shared by a group of four lanes: three hash rounds
        # for the program instead of seven (the 2nd and 3rd stages hash one counter per lane), the
        # words moving between lanes by block-wide integer sums of one nonzero term (exact). Under
        # domain randomisation a group is eight lanes (group_lanes), so that the pose's four uniforms
        # and the ranges' four keys share one round: four rounds instead of sixteen, where groups of
        # four would take five.
        lane = jax.lax.iota(jnp.int32, block)
        slot, group = lane % group_lanes, lane // group_lanes
        i32 = lambda v: jax.lax.bitcast_convert_type(v, jnp.int32)  # noqa: E731
        u32 = lambda v: jax.lax.bitcast_convert_type(v, jnp.uint32)  # noqa: E731
        take = lambda at, v: jnp.sum(jnp.where(at, v, 0))  # noqa: E731  (the value of the lane at `at`)
        k_reset = [i32(v) for v in _subkey(key, 4)]  # each lane its own env's

        def to_groups(m, c):  # the m-th done lane (in lane order) hands its reset key to group m
            pending, owner, g0, g1 = c
            src = jnp.min(jnp.where(pending, lane, block))
            at, mine = lane == src, group == m
            return (pending & ~at, jnp.where(mine, src, owner), jnp.where(mine, take(at, k_reset[0]), g0),
                    jnp.where(mine, take(at, k_reset[1]), g1))

        zi = jnp.zeros_like(lane)
        _, owner, g0, g1 = jax.lax.fori_loop(0, n_done, to_groups, (done, zi, zi, zi))
        zero = jnp.zeros_like(key[0])
        # Slot 0: the env key, 1: the pose key, and under domain randomisation 2: the draws' base key
        # (randomise.draw's fold of the reset key with the draw tag).
        counter = jnp.where(slot == 2, jnp.uint32(randomise.DRAW_TAG), u32(slot)) if domain else u32(slot)
        b = [i32(v) for v in rng.threefry2x32(u32(g0), u32(g1), zero, counter)]

        def to_group(m, c):  # slot j's key to every lane of group m: the pose key, the draws' base key
            mine = group == m
            return tuple(jnp.where(mine, take(lane == group_lanes * m + j, b[w]), cw)
                         for (j, w), cw in zip(shared, c))

        shared = [(1, 0), (1, 1)] + ([(2, 0), (2, 1)] if domain else [])
        got = jax.lax.fori_loop(0, n_done, to_group, (zi,) * len(shared))
        if domain:
            # Slots 0-3 hash the pose's uniform `slot` from the pose key; slot 4 + i range i's key from
            # the draws' base key (fold 2 i, as draws() does), then its uniform, scaled to its bounds.
            pose = slot < 4
            h = rng.threefry2x32(jnp.where(pose, u32(got[0]), u32(got[2])), jnp.where(pose, u32(got[1]), u32(got[3])),
                          zero, u32(jnp.where(pose, slot, 2 * (slot - 4))))
            low = high = jnp.zeros(slot.shape, jnp.float32)
            for i in range(len(domain)):
                low = jnp.where(slot == 4 + i, f(f"rand_low{i}"), low)
                high = jnp.where(slot == 4 + i, f(f"rand_high{i}"), high)
            drawn = _drawn_from(h, low, high)
        else:
            h = rng.threefry2x32(u32(got[0]), u32(got[1]), zero, u32(slot))
        noise = self.noise_of(*h)
        value = jnp.where(slot == 0, f("init_pos") + noise,
                          jnp.where(slot == 2, f("init_pole_angle") + noise, noise))
        # Back to the done lane: slot j's value (x, xd, th, thd), slot 0's env key and slot 4 + i's range.
        sources = [(j, i32(value)) for j in range(4)] + [(0, b[0]), (0, b[1])]
        sources += [(4 + i, i32(drawn)) for i in range(len(domain))] if domain else []

        def to_owner(m, c):
            dest = lane == take(lane == group_lanes * m, owner)
            return tuple(jnp.where(dest, take(lane == group_lanes * m + j, v), cj)
                         for (j, v), cj in zip(sources, c))

        v = jax.lax.fori_loop(0, n_done, to_owner, (zi,) * len(sources))
        as_f = lambda w: jax.lax.bitcast_convert_type(w, jnp.float32)  # noqa: E731
        return (as_f(v[0]), as_f(v[2]), as_f(v[1]), as_f(v[3]), u32(v[4]), u32(v[5]),
                *(as_f(w) for w in v[6:]))

    # ---- the step's phases -------------------------------------------------------------------------------------
    def step(self, cr):
        """One training step of the program's envs (``cr``: the carry's columns by name): the phases in order,
        ``v`` gathering the step's values by name as each phase adds them."""
        cr = dict(cr)
        v = {"key": (cr["k0"], cr["k1"])}
        v.update(self.act(cr, v["key"]))
        v.update(self.env_step(cr, v["command"]))
        v.update(self.learn(cr, v))
        v.update(self.record(cr, v))
        self.write_back(cr, v, self.reset(cr, v))
        return cr

    def act(self, cr, key):
        """The step's keys, whether the env is within the run's budget (Trainer._active: steps per env under
        total_steps, else episodes per env), the epsilon-greedy action on the carried row and the task's command."""
        st, f = self.st, self.f
        k_next, k_act = _subkey(key, 0), _subkey(key, 1)
        active = cr["env_steps"] < st.steps_budget if st.steps_budget else cr["episode"] < st.nepisodes
        r_s = [cr[f"r{k}"] for k in range(st.n_actions)]
        a = _epsilon_greedy(k_act, r_s, cr["epsilon"], st.n_actions)
        delta = jnp.zeros_like(cr["command"])
        for i, v in enumerate(st.action_steps):
            delta = jnp.where(a == i, jnp.float32(v), delta)
        command = command_after(cr["command"], delta, f("pos_step"), f("max_base_velocity"), jnp)
        return dict(k_next=k_next, active=active, a=a, command=command)

    def physics(self, x, th, xd, thd, ctrl, factors, written_out=False):
        """One substep: the simulator's own equations (CartPoleSim.coordinate_step) on [block] vectors, with the
        written-out sin/cos where asked and, under domain randomisation, each env's drawn factors; the one
        actuator takes the command."""
        sincos = self.st.written.sincos if written_out else None
        return self.st.coordinate_step(x, th, xd, thd, (ctrl,), sincos, factors)

    def env_step(self, cr, command):
        """env.step after the action: the physics' substeps, the NaN guard, the observation, the task's outcome and
        reward, truncation and (randomised) the observation's noise."""
        st, f = self.st, self.f
        x, th, xd, thd = cr["x"], cr["th"], cr["xd"], cr["thd"]
        # The episode's drawn factors (Robot.sim_physics: 1 for a quantity the task does not draw).
        factors = {n: cr[n] if n in st.domain else 1.0 for n in _physics_names()} if st.domain else None

        def substeps(written_out):
            state = (x, th, xd, thd)
            for _sub in range(st.n_substeps):
                state = self.physics(*state, command, factors, written_out)
            return state

        if st.written is not None:
            # The written-out sin/cos serve the step where every env's angle stays within their range in every
            # substep (checked once per step and program); otherwise the step is redone with the calls.
            state, beyond = (x, th, xd, thd), jnp.zeros(x.shape, jnp.int32)
            for _sub in range(st.n_substeps):
                beyond = beyond | (~(jnp.abs(state[1]) <= st.written.limit)).astype(jnp.int32)  # NaN too
                state = self.physics(*state, command, factors, True)
            x, th, xd, thd = jax.lax.cond(jnp.max(beyond) > 0, lambda _: substeps(False), lambda _: state, None)
        else:
            x, th, xd, thd = substeps(False)
        ok = _finite(x) & _finite(th) & _finite(xd) & _finite(thd)
        obs = (x, xd, th, thd)
        ok = ok & _finite(obs[0]) & _finite(obs[1]) & _finite(obs[2]) & _finite(obs[3])
        term = fell(obs[0], obs[2], f("min_base_pose_x"), f("max_base_pose_x"), f("min_pole_angle"),
                    f("max_pole_angle"))
        obs = tuple(jnp.where(ok, o, cr[f"o{d}"]) for d, o in enumerate(obs))
        reward = jnp.where(ok, jnp.float32(1.0), jnp.float32(0.0))
        term = term | ~ok
        env_steps_now = cr["steps"] + 1
        trunc = (env_steps_now >= self.max_episode_steps) & ~term
        pnan = ~ok
        if st.noise_on:  # what the agent sees (TaskEnv.step: after the guard; termination read the true state)
            std = cr[randomise.OBS_NOISE]
            # A program whose envs all draw no noise skips its hashes (one scalar branch): obs + 0 * z is obs
            # (z is finite), up to the sign of a zero.
            obs = jax.lax.cond(_any(std > 0), lambda o: _noisy(o, (cr["nk0"], cr["nk1"]), env_steps_now, std),
                               lambda o: o, obs)
        return dict(state=(x, th, xd, thd), obs=obs, reward=reward, term=term, trunc=trunc, pnan=pnan,
                    steps=env_steps_now)

    def learn(self, cr, v):
        """The next state's row, the episode's end, and Q-learning's update of (s, a) with the rows carried across
        the step (the next state's row sees the update where it is the same row)."""
        st, f = self.st, self.f
        a, obs, reward, term, trunc, pnan, active = (v[n] for n in ("a", "obs", "reward", "term", "trunc", "pnan",
                                                                   "active"))
        env_steps_now = v["steps"]
        s2 = self.discretise(obs)
        done = term | trunc | (env_steps_now >= st.nsteps)
        r_s2 = self.row(s2)
        r_s = [cr[f"r{k}"] for k in range(st.n_actions)]
        discount = f("gamma") * (1.0 - term.astype(jnp.float32))
        target = reward + discount * _row_max(r_s2)
        old = r_s[0]
        for i in range(1, st.n_actions):
            old = jnp.where(a == i, r_s[i], old)
        new = old + f("alpha") * (target - old)
        written = jnp.where(active & ~pnan, new, old)
        hit_s = s2 == cr["s"]
        r_s2 = [jnp.where(hit_s & (a == k), written, r_s2[k]) for k in range(st.n_actions)]
        return dict(s2=s2, done=done, r_s2=r_s2, written=written)

    def record(self, cr, v):
        """A finished episode's return, length and termination: into the records (under the step budget an env
        records its first nepisodes episodes and counts the rest), or summed in the carry with records off."""
        from jax.experimental.pallas import triton as plgpu

        st = self.st
        reward, term, done, active, env_steps_now = (v[n] for n in ("reward", "term", "done", "active", "steps"))
        ep_return = cr["ep_return"] + reward
        record = done & active
        if st.records:
            slot = jnp.minimum(cr["episode"], st.nepisodes - 1)
            at = self.env * st.n_rec + slot
            kept = record & (cr["episode"] < st.nepisodes) if st.steps_budget else record
            plgpu.store(self.rec_refs[0].at[at], ep_return, mask=kept)
            plgpu.store(self.rec_refs[1].at[at], env_steps_now, mask=kept)
            plgpu.store(self.rec_refs[2].at[at], term.astype(jnp.int32), mask=kept)
        else:
            cr["ret_sum"] = cr["ret_sum"] + jnp.where(record, ep_return, 0.0)
            cr["len_sum"] = cr["len_sum"] + jnp.where(record, env_steps_now, 0)
            cr["term_any"] = cr["term_any"] | (record & term).astype(jnp.int32)
        return dict(ep_return=ep_return, record=record)

    def reset(self, cr, v):
        """The fresh episode wherever done (env.reset from the reset key) and its rows from the updated table, as
        one tuple (:meth:`write_back` reads it). Seven of the step's ten hashes serve only the reset, and in many
        steps no env of a program is done: under ``skip_resets`` the program computes them only when one of its
        envs is (a scalar branch, scf.if in Triton); where none is, the fresh values would be discarded by the
        selects of :meth:`write_back` anyway."""
        st = self.st
        key, a, done, s2, written, env_steps_now = (v[n] for n in ("key", "a", "done", "s2", "written", "steps"))
        x = v["state"][0]
        n_actions, domain = st.n_actions, st.domain

        def fresh_episode(hashed):
            fresh_x, fresh_th, fresh_xd, fresh_thd, rk0, rk1 = hashed[:6]
            drawn = hashed[6:]  # the fresh episode's domain, in the order of ``domain``
            obs_fresh = (fresh_x, fresh_xd, fresh_th, fresh_thd)
            episode_key = ()
            if st.noise_on:  # env.reset's observation, noisy from the fresh env key at step 0
                std = drawn[domain.index(randomise.OBS_NOISE)]

                def with_noise(o):
                    k = _subkey((rk0, rk1), randomise.NOISE_TAG)
                    return (*_noisy(o, k, jnp.zeros_like(env_steps_now), std), *k)

                def without_noise(o):  # the episode key serves only a noise level above 0: left unhashed
                    return (*o, jnp.zeros_like(rk0), jnp.zeros_like(rk1))

                # A program whose fresh episodes all drew no noise skips the six hashes (a scalar branch), as
                # the step skips its five: obs + 0 * z is obs up to the sign of a zero.
                fresh = jax.lax.cond(_any(done & (std > 0)), with_noise, without_noise, obs_fresh)
                obs_fresh, episode_key = fresh[:4], fresh[4:]
            s_fresh = self.discretise(obs_fresh)
            r_fresh = self.row(s_fresh, done)
            r_fresh = [jnp.where((s_fresh == cr["s"]) & (a == k), written, r_fresh[k]) for k in range(n_actions)]
            extra = (*obs_fresh, *drawn, *episode_key) if domain else ()
            return (fresh_x, fresh_th, fresh_xd, fresh_thd, rk0, rk1, s_fresh, *r_fresh, *extra)

        if st.skip_resets:
            def none_done(_):
                zf, zu = jnp.zeros_like(x), jnp.zeros_like(key[0])
                extra = ([zf] * (4 + len(domain)) + [zu] * (2 * st.noise_on)) if domain else []
                return (zf, zf, zf, zf, zu, zu, jnp.zeros_like(s2), *([zf] * n_actions), *extra)

            n_done = jnp.sum(done.astype(jnp.int32))
            if st.group_resets and st.block >= st.group_lanes:  # a group per done env while there are enough
                some_done = lambda n: fresh_episode(jax.lax.cond(  # noqa: E731
                    n <= st.block // st.group_lanes, lambda m: self.hashed_by_group(key, done, m),
                    lambda m: self.hashed_by_lane(key), n))
            else:
                some_done = lambda n: fresh_episode(self.hashed_by_lane(key))  # noqa: E731
            reset = jax.lax.cond(n_done > 0, some_done, none_done, n_done)
        else:
            reset = fresh_episode(self.hashed_by_lane(key))
        return reset

    def write_back(self, cr, v, reset):
        """The updated table entry to memory, and the step's carry: the fresh episode's values where done, the
        step's elsewhere."""
        from jax.experimental.pallas import triton as plgpu

        st, f = self.st, self.f
        n_actions, domain = st.n_actions, st.domain
        x, th, xd, thd = v["state"]
        a, obs, reward, term, trunc, pnan, env_steps_now, command, s2, done, r_s2, written, active, ep_return, \
            record, k_next = (v[n] for n in ("a", "obs", "reward", "term", "trunc", "pnan", "steps", "command", "s2",
                                             "done", "r_s2", "written", "active", "ep_return", "record", "k_next"))
        fresh, rk, s_fresh, r_fresh = reset[:4], reset[4:6], reset[6], reset[7:7 + n_actions]
        plgpu.store(self.q_ref.at[self.row_at(cr["s"]) + a], written)
        w = lambda new_, cur: jnp.where(done, new_, cur)  # noqa: E731
        cr["x"], cr["th"], cr["xd"], cr["thd"] = w(fresh[0], x), w(fresh[1], th), w(fresh[2], xd), w(fresh[3], thd)
        if domain:  # the fresh episode's (noisy) observation and its drawn domain
            obs_fresh, drawn = reset[7 + n_actions:11 + n_actions], reset[11 + n_actions:]
            cr["o0"], cr["o1"], cr["o2"], cr["o3"] = (w(o_new, o) for o_new, o in zip(obs_fresh, obs))
            for name, value in zip(domain, drawn):
                cr[name] = w(value, cr[name])
            if st.noise_on:
                cr["nk0"], cr["nk1"] = w(drawn[-2], cr["nk0"]), w(drawn[-1], cr["nk1"])
        else:
            cr["o0"], cr["o1"], cr["o2"], cr["o3"] = (w(fresh[0], obs[0]), w(fresh[2], obs[1]),
                                                      w(fresh[1], obs[2]), w(fresh[3], obs[3]))
        cr["reward"] = w(jnp.float32(0.0), reward)
        cr["term"] = w(0, term.astype(jnp.int32))
        cr["trunc"] = w(0, trunc.astype(jnp.int32))
        cr["steps"] = w(0, env_steps_now)
        cr["command"] = w(jnp.float32(0.0), command)
        cr["ek0"], cr["ek1"] = w(rk[0], cr["ek0"]), w(rk[1], cr["ek1"])
        cr["pnan"] = w(0, pnan.astype(jnp.int32))
        cr["s"] = w(s_fresh, s2)
        for k in range(n_actions):
            cr[f"r{k}"] = w(r_fresh[k], r_s2[k])
        eps = cr["epsilon"]
        cr["epsilon"] = w(jnp.where(eps > f("epsilon_min"), eps * f("epsilon_discount"), eps), eps)
        cr["action"] = a
        cr["episode"] = cr["episode"] + record.astype(jnp.int32)
        cr["ep_return"] = w(jnp.float32(0.0), ep_return)
        cr["k0"], cr["k1"] = k_next
        cr["nan_episodes"] = cr["nan_episodes"] + (record & pnan).astype(jnp.int32)
        cr["env_steps"] = cr["env_steps"] + active.astype(jnp.int32)


def _block_for(n: int, cap: int | None = None) -> int:
    """The largest power of two that divides ``n``, at most ``cap`` (default :data:`BLOCK`)."""
    cap = BLOCK if cap is None else cap
    block = 1
    while block < cap and n % (2 * block) == 0:
        block *= 2
    return block


def run_chunk(trainer: Any, runner: Any, agent_params: Any, env_params: Any, written: Any = None) -> Any:
    """``trainer.run_chunk`` as one Pallas kernel (the values of :meth:`jaxrobo.training.trainer.Trainer.step`,
    scanned ``chunk_steps`` times), for a run :func:`unsupported_run` takes. Interpreted on a CPU, compiled through
    Triton on a GPU. ``written``: the written-out ``sin``/``cos`` with the range they hold on (``.sincos``,
    ``.limit``: :func:`jaxrobo.physics.libdevice_sincos.written_out`), which the trainer hands over under the plan's
    ``fast_sincos`` on a GPU where they were checked; None: libdevice's calls."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    plan = trainer.plan
    c, env, disc = trainer.config, trainer.env, trainer.disc
    n, n_states, n_actions = c.n_envs, disc.n_states, trainer.n_actions
    sim = env.robot.sim
    records = c.record_episodes
    n_rec = runner.returns.shape[1]
    ep = env_params
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    fvals = [f32(getattr(ep, name)) for name in _F[:9]]
    fvals += [f32(getattr(agent_params, name)) for name in ("alpha", "gamma", "epsilon_discount", "epsilon_min")]
    fvals += [disc.low[d] for d in range(4)] + [disc.width[d] for d in range(4)]
    # Domain randomisation: the quantities the task draws (its ranges, in order) and each range's bounds.
    domain = tuple(randomise.range_fields(type(ep))) if env.randomised else ()
    for bounds in randomise.ranges(ep).values() if domain else ():
        bounds = jnp.asarray(bounds, jnp.float32)
        fvals += [bounds[0], bounds[1]]
    fvals += [jnp.float32(0.0)] * (_PARAMS - len(fvals))  # Triton blocks are powers of two long
    fp = jnp.stack([jnp.reshape(v, ()).astype(jnp.float32) for v in fvals])
    ip = jnp.reshape(jnp.asarray(ep.max_episode_steps, jnp.int32), (1,))

    es = runner.env_state
    ps = es.pipeline_state
    ekey = jax.random.key_data(es.key)
    key = jax.random.key_data(runner.key)
    if runner.q_rows is None:
        rows = runner.agent.q[jnp.arange(n), 0, runner.s, :]
    else:
        rows = runner.q_rows[:, 0, :]
    i32 = lambda v: jnp.asarray(v).astype(jnp.int32)  # noqa: E731
    cols = dict(x=ps.qpos[:, 0], th=ps.qpos[:, 1], xd=ps.qvel[:, 0], thd=ps.qvel[:, 1],
                o0=es.obs[:, 0], o1=es.obs[:, 1], o2=es.obs[:, 2], o3=es.obs[:, 3], reward=es.reward,
                term=i32(es.terminated), trunc=i32(es.truncated), steps=es.steps, command=es.task.command,
                ek0=ekey[:, 0], ek1=ekey[:, 1], pnan=i32(es.physics_nan), s=runner.s,
                action=runner.action, epsilon=runner.epsilon, episode=runner.episode, ep_return=runner.ep_return,
                k0=key[:, 0], k1=key[:, 1], nan_episodes=runner.nan_episodes, env_steps=runner.env_steps)
    for k in range(4):
        cols[f"r{k}"] = rows[:, k] if k < n_actions else jnp.zeros(n, jnp.float32)
    if records:
        cols.update(ret_sum=jnp.zeros(n, jnp.float32), len_sum=jnp.zeros(n, jnp.int32),
                    term_any=jnp.zeros(n, jnp.int32))
    else:
        cols.update(ret_sum=runner.returns[:, 0], len_sum=runner.lengths[:, 0], term_any=i32(runner.terminated[:, 0]))
    cols.update({name: es.domain[name] for name in domain})
    if randomise.OBS_NOISE in domain:
        noise_key = jax.random.key_data(jax.vmap(lambda k: jax.random.fold_in(k, randomise.NOISE_TAG))(es.key))
        cols.update(nk0=noise_key[:, 0], nk1=noise_key[:, 1])
    columns = _columns(domain)
    col_in = [jnp.asarray(cols[name]).astype(dtype) for name, dtype in columns]
    block = _block_for(n, plan.fused_block)
    q_in = runner.agent.q.reshape(n, n_states, n_actions)
    big = [q_in.reshape(-1)]
    if records:
        big += [runner.returns.reshape(-1), runner.lengths.reshape(-1), i32(runner.terminated).reshape(-1)]

    strides = tuple(int(v) for v in np.cumprod((disc.bins[1:] + (1,))[::-1])[::-1])
    static = _Static(block, c.chunk_steps, n_states, n_actions, n_rec, records, c.nepisodes, c.nsteps, strides,
                     tuple(int(b) for b in disc.bins), sim.coordinate_step, int(sim.n_substeps),
                     tuple(float(v) for v in np.asarray(env._steps)), plan.skip_resets, plan.group_resets, written,
                     trainer.steps_per_env if trainer.budget == "steps" else 0, domain)
    kernel = _make_kernel(static)
    col_spec = pl.BlockSpec((block,), lambda i: (i,))
    whole = pl.BlockSpec(memory_space=pl.ANY)
    n_cols = len(columns)
    in_specs = ([pl.BlockSpec((_PARAMS,), lambda i: (0,)), pl.BlockSpec((1,), lambda i: (0,))]
                + [col_spec] * n_cols + [whole] * len(big))
    out_specs = [col_spec] * n_cols + [whole] * len(big)
    out_shape = [jax.ShapeDtypeStruct((n,), dtype) for _, dtype in columns] + \
                [jax.ShapeDtypeStruct(b.shape, b.dtype) for b in big]
    aliases = {2 + n_cols + i: n_cols + i for i in range(len(big))}
    interpret = jax.default_backend() != "gpu"
    # Triton, not Mosaic GPU: the kernel gathers and scatters single words by computed index, which Triton's
    # pointer arithmetic does and Mosaic GPU's bulk copies do not.
    warps = max(1, min(8, block // 32))  # one thread per env
    params = None if interpret else plgpu.CompilerParams(num_warps=warps, num_stages=1)
    outs = pl.pallas_call(kernel, out_shape=out_shape, grid=(n // block,), in_specs=in_specs, out_specs=out_specs,
                          input_output_aliases=aliases, interpret=interpret, compiler_params=params,
                          name="cartpole_qlearn_chunk")(fp, ip, *col_in, *big)
    o = dict(zip((name for name, _ in columns), outs[:n_cols]))
    big_out = outs[n_cols:]
    boolean = lambda v: v.astype(bool)  # noqa: E731
    impl = jax.random.key_impl(runner.key)
    env_state = EnvState(
        JointState(jnp.stack([o["x"], o["th"]], 1), jnp.stack([o["xd"], o["thd"]], 1)),
        jnp.stack([o["o0"], o["o1"], o["o2"], o["o3"]], 1), o["reward"], boolean(o["term"]), boolean(o["trunc"]),
        o["steps"], type(es.task)(command=o["command"]),
        jax.random.wrap_key_data(jnp.stack([o["ek0"], o["ek1"]], 1), impl=impl), boolean(o["pnan"]),
        **({"domain": {name: o[name] for name in domain}} if domain else {}))
    q = big_out[0].reshape(runner.agent.q.shape)
    q_rows = None
    if runner.q_rows is not None:
        q_rows = jnp.stack([o[f"r{k}"] for k in range(n_actions)], 1)[:, None, :]
    if records:
        returns = big_out[1].reshape(runner.returns.shape)
        lengths = big_out[2].reshape(runner.lengths.shape)
        terminated = boolean(big_out[3].reshape(runner.terminated.shape))
    else:
        returns = runner.returns.at[:, 0].set(o["ret_sum"])
        lengths = runner.lengths.at[:, 0].set(o["len_sum"])
        terminated = runner.terminated.at[:, 0].set(boolean(o["term_any"]))
    return runner.replace(env_state=env_state, agent=AgentState(q, runner.agent.visited), s=o["s"], q_rows=q_rows,
                  action=o["action"], epsilon=o["epsilon"], episode=o["episode"], ep_return=o["ep_return"],
                  key=jax.random.wrap_key_data(jnp.stack([o["k0"], o["k1"]], 1), impl=impl),
                  returns=returns, lengths=lengths, terminated=terminated, nan_episodes=o["nan_episodes"],
                  env_steps=o["env_steps"])


class ChunkKernel(NamedTuple):
    """A task's whole training chunk as one kernel (:attr:`jaxrobo.task.env.TaskEnv.chunk_kernel`)."""

    #: ``(env, config, agent, discretiser, fused_block) -> str | None``: why a run cannot take it (None: it can).
    unsupported_run: Callable[..., str | None]
    #: ``(trainer, runner, agent_params, env_params, written) -> runner``: one chunk.
    run_chunk: Callable[..., Any]


#: What :class:`envs.cartpole.stay_up.CartPoleStayUp` offers as its ``chunk_kernel``.
CHUNK_KERNEL = ChunkKernel(unsupported_run, run_chunk)
