"""Write docs/results.md, the one page of measured figures, from the benchmark JSON under benchmarks/results/.

    python benchmarks/results_page.py                  # rewrite docs/results.md
    python benchmarks/results_page.py --check          # exit 1 if docs/results.md is not what the JSON gives

Every JSON file under ``benchmarks/results/<device>/`` (the git-ignored ``local/`` excepted) becomes one section of
its device: the device and the command that measured it as the JSON records them, then its rows as a table (the
throughput rows with their rates and like-for-like ratios, as ``benchmarks/throughput.py`` computes them), or its
top-level figures. Figures are never typed into this page by hand: to change one, run the benchmark again with
``--out benchmarks/results/<device>`` and rerun this script. Nothing here imports JAX.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results")
PAGE = os.path.join(ROOT, "docs", "results.md")
if HERE not in sys.path:
    sys.path.insert(0, HERE)

import throughput  # noqa: E402  (its ratios and rate format, so this page and its tables agree)

#: What each benchmark file is, by its name (the scripts' default names); a file not listed is named by its path.
WHAT = {
    "throughput.json": "Throughput (`benchmarks/throughput.py`, the main job): env steps per second with the "
                       "learner in the loop, beside the peers",
    "throughput_mjx_sizes.json": "Throughput of the MJX cart-pole over batch sizes (`benchmarks/throughput.py`)",
    "arm_throughput.json": "Throughput of ArmReach-v0 (`benchmarks/throughput.py --envs ArmReach-v0`)",
    "p9_cartpole_analytic.json": "The user's commands end to end, analytic cart-pole (`benchmarks/throughput.py "
                                 "--commands`)",
    "p9_mjx_goto.json": "The user's commands end to end, MJX cart-pole and QuadcopterGoto-v2 "
                        "(`benchmarks/throughput.py --commands`)",
    "time_to_learn.json": "Time to learn (`benchmarks/time_to_learn.py`): training seconds until the greedy policy "
                          "meets the task's target",
    "time_to_learn_analytic.json": "Time to learn on the analytic backend (`benchmarks/time_to_learn.py`)",
    "time_to_trained.json": "Time to a trained robot (`benchmarks/time_to_trained.py`): each task's default "
                            "`jaxrobo train --env ID`, start to exit, in fresh processes",
    "sweep.json": "Many independent runs in one sweep call (`benchmarks/sweep.py`)",
    "sweep_analytic.json": "Many independent runs in one sweep call, analytic backend (`benchmarks/sweep.py`)",
    "startup.json": "Start-up to the first training chunk, fresh and cached (`benchmarks/startup.py`)",
    "run_end_ab.json": "Whole commands before and after a change, alternating on one machine (the wall line's parts)",
    "run_end_ab_tables.json": "A run's end before and after the checkpoint's tables file is written beside the "
                              "records' cut, alternating on one machine (the wall line's parts)",
    "run_end_ab_s14.json": "A run's end before and after the records' Fortran-ordered padding and the tables' "
                           "file in a thread (CPU-measured changes), alternating on a GPU host",
    "run_end_ab_s15.json": "A run's end before and after the checkpoint's file is written beside its tables (and, "
                           "on a GPU, the records' host copies start first), alternating; host copy rates",
    "run_end_ab_s16.json": "A run's end before and after the tables cross to the host as their nonzero entries (and "
                           "the summary is computed beside the episode files), alternating",
    "run_end_cpu_s17.json": "Where a 65,536-env run's end goes, with the host's CPU seconds: the tables' file, the "
                            "summary's figures and the episode files side by side",
    "autotune_off.json": "A tabular run's files with XLA's GPU autotuning on and off, alone and after other tasks' "
                         "compiles (ExecutionPlan.fixed_kernels)",
    "startup_s17.json": "Where a warm default command's start-up goes on a GPU host: imports by -X importtime, "
                        "JAX's import and device discovery",
    "time_to_trained_s18.json": "Time to a trained robot (`benchmarks/time_to_trained.py`) again, at the shared "
                                "traces, on another H200 host",
    "traces_shared.json": "The random hash and each env's reset traced once per process, not at every draw and "
                          "reset a program holds: cold compiles before and after, the files' bytes",
    "compile_split_s18.json": "Where a default GPU run's compile goes, cold (XLA's own timers) and warm (JAX's "
                              "monitoring events), and the XLA levers tried on it",
    "record_parts.json": "The summary's figures and the episode statistics' percentiles from parts computed on the "
                         "device: the cart-pole's writing at 65,536 and 1 M envs before and after, the same numbers",
    "records_linked.json": "The closing checkpoint's records file linked as the results' records.npz: the "
                           "cart-pole's writing at 65,536 and 1 M envs before and after, the same numbers, timelines",
    "writing_levers_s22.json": "What a 1 M-env run's writing spends its CPU on (each thread's CPU seconds) and "
                                "six levers tried on it (the disk, the switch interval, the block, the threads, "
                                "the copies' order, the statistics' sums beside the copies), none adopted",
    "writing_bound_s23.json": "How far the tables as mask and nonzero values and the statistics' sums left out "
                              "would take a 1 M-env run's writing (prototypes, measured, neither adopted)",
    "zlib_ng.json": "The .npz writer's deflate and CRC-32 on zlib-ng: the cart-pole's writing at 65,536 and 1 M envs "
                    "before and after, file sizes, the arrays' hashes, 8 MB blocks on one core, each writer's timeline",
    "hash_kernel.json": "The random hash as jaxlib's GPU threefry kernel (ExecutionPlan.hash_kernel): cold and warm "
                        "compiles of the default runs and a sweep before and after, large batches' run time, the "
                        "files' bytes, a sweep's rows on one and two GPUs",
    "fixed_kernels_devices.json": "XLA's GPU autotuning off (fixed_kernels) with --devices 2 and a sweep on two "
                                  "GPUs: one GPU's bytes and rows",
    "mjx_step_traced_once.json": "MJX's step traced once per process (not again for the greedy flights): the "
                                 "default commands' traces and compile before and after, alternating",
    "device_eval_one_device.json": "A split run's greedy flights on its first device with the one-device "
                                   "programs: evaluation seconds and figures against one GPU",
    "device_splits_one_program.json": "Training split over GPUs with each device's one-device program, against "
                                      "one GPU: tables, records and figures compared",
    "startup_analytic.json": "Start-up on the analytic backend (`benchmarks/startup.py`)",
    "ros_sim2sim.json": "The exported policies flown in native MuJoCo (`scripts/sim2sim.py`) and through ROS 1 "
                        "(`jaxrobo ros sim` with the policy node): docs/real_robot.md's and docs/ros.md's commands "
                        "(`benchmarks/ros_sim2sim.py`)",
    "arm_learning.json": "ArmReach-v0 learning over independent runs (`benchmarks/arm_learning.py`)",
    "goto_learning.json": "QuadcopterGoto-v1 learning over independent runs (`benchmarks/goto_learning.py`)",
    "adapter_latency.json": "Gymnasium adapter latency, one env and vectorised (`benchmarks/adapter_latency.py`)",
    "ppo_goto.json": "PPO on QuadcopterGotoTwist-v0 (`benchmarks/ppo_goto.py`)",
    "ppo_goto_nocache.json": "PPO on QuadcopterGotoTwist-v0 with an empty compile cache (`benchmarks/ppo_goto.py`)",
    "ppo_throughput.json": "PPO training throughput beside Brax's own env (`benchmarks/studies/ppo_throughput.py`)",
    "env_groups.json": "MJX batches stepped in groups (`benchmarks/studies/env_groups.py`)",
    "libdevice_sincos.json": "The kernel's sin/cos against libdevice's, bit for bit "
                             "(`benchmarks/studies/libdevice_sincos.py`)",
    "scale_train.json": "`jaxrobo train` over several GPUs of one host (`benchmarks/scale_out.py`)",
    "scale_train_dist.json": "`jaxrobo train`, one process per GPU (`benchmarks/scale_out.py --distributed`)",
    "scale_sweep.json": "`jaxrobo sweep` over several GPUs of one host (`benchmarks/scale_out.py`)",
    "scale_sweep_dist.json": "`jaxrobo sweep`, one process per GPU (`benchmarks/scale_out.py --distributed`)",
    "default_learning_16_seeds.json": "Each tabular task's default command on 16 seeds (learning figure on fresh "
                                      "episodes)",
    "learners_compare.json": "The cart-pole's four learners (Double Q also with a shared table) and the seed preset, "
                             "docs/cartpole.md's 'What it learns', 16 learners each (`benchmarks/learners_compare.py`)",
    "scale_sweep_2gpu.json": "`jaxrobo sweep` on 1 GPU, 2 GPUs and 2 processes: the same rows on each (a step "
                             "of 64 envs a row launches the same kernels on half the rows, so the run scales "
                             "sublinearly)",
    "scale_sweep_4gpu.json": "`jaxrobo sweep` (Goto-v2, 4 configurations x 1,024 seeds x 64 envs) on 1, 2 and 4 GPUs "
                             "and 4 processes: the same rows on each; the run scales sublinearly because a "
                             "GPU stepping its share (65,536 envs on four) reaches about half the env steps per "
                             "second that one GPU reaches with the whole batch",
    "compile_beside.json": "Goto-v2's and the arm's default commands, cold and warm, before and after the "
                           "evaluation compiles beside the training chunk (`ExecutionPlan.compile_beside`), one call",
    "reuse_traces.json": "The tabular default commands warm, traces read back (`ExecutionPlan.reuse_traces`) and "
                         "traced afresh, alternating in one call on one cache (`jaxrobo.speed.reuse`)",
    "xla_autotune_cold.json": "Goto-v2's and the arm's default commands cold with XLA's GPU autotuning as it is, at "
                              "level 0, and without Triton GEMM fusions (one call)",
    "startup_seed_key_s31.json": "The tabular default commands before and after the run's key is written on the "
                                 "host and the kept traces' key resolves each file once, alternating on an H200",
    "startup_s31.json": "The tabular default commands' start-up on a lent GPU host with the bytecode compiled, and "
                        "ml_dtypes' import beside numpy 2.5.2 (0.6.0 and 0.7.0)",
    "startup_seed_key.json": "The tabular default commands' start-up before and after the run's key is written on "
                             "the host (rng.seed_key) and the kept traces' key resolves each file once, alternating",
    "ml_dtypes_import.json": "ml_dtypes 0.7.0 against 0.6.0 beside numpy 2.4.6 on 2 CPU cores: its import and the "
                             "tabular default commands' start-up, alternating",
    "startup_imports_s30.json": "A lent GPU host's imports and device discovery, timed in fresh processes, beside "
                                "the tabular default commands' warm start-up",
    "compile_flags_s30.json": "The arm's and Goto-v2's default commands cold and warm without and with a "
                              "process-wide --xla_gpu_autotune_level=0 (the plan's programs compile at level 0 "
                              "already), alternating, and whether XLA's LLVM-module split is a flag of this jaxlib",
    "ppo_twist_warm_profile.json": "Where a warm QuadcopterGotoTwist-v0 PPO run's wall goes: its evaluation points' "
                                   "seconds and JAX's compile log",
    "stop_latency.json": "PPO and SAC stopped by SIGINT on a GPU: how soon they exit, what they keep, the resume",
    "step_budget_65536.json": "The 65,536-env cart-pole run under a step budget, cold and warm: where its wall goes "
                              "(the run stops at the learning target)",
    "train_two_processes_s24.json": "`jaxrobo train` as two processes (jax.distributed, one GPU each) against one "
                                    "process on one GPU after the multi-process fixes: exit codes, checksums",
    "step_budget_s24.json": "The 65,536- and 1 M-env cart-pole runs under a step budget at 1a0aaff, cold "
                            "and warm: the wall's parts (writing at both sizes against the issue's 1 s and 3 s)",
    "compile_init_beside.json": "The tabular default commands cold and warm, before and after the first carry's "
                                "program compiles beside the training chunk (`ExecutionPlan.compile_beside`), one call",
    "writing_parallel.json": "Writing at 65,536 and 1 M envs before and after the `.npz` blocks are checksummed and "
                             "deflated by a thread per core (`jaxrobo.io.npz.write_npz_deflated`) and the records "
                             "cross cut to their written columns (`cut_records`), two calls; the tables file's A/B",
    "arm_analytic_s32.json": "ArmReach-v0's default command on MJX (the code before) and on its closed form (the new "
                             "default), alternating, and the closed form's default on 16 seeds",
    "locked_copy_s34.json": "A 1 M-env run's records crossing to the host through page-locked memory "
                            "(`jaxrobo.speed.locked_copy`) against `jax.device_get`: the copy alone by each path, "
                            "the whole command alternating, timelines of its writing, and a prototype not adopted",
    "device_deflate_s35.json": "A 1 M-env run's tables deflated on the device (`jaxrobo.speed.device_deflate`) "
                               "against the host's threads: the encoder alone, the whole command alternating with "
                               "the code before (and at 65,536 envs, where the host path stays), timelines",
    "direct_writes_s36.json": "A 1 M-env run's writing with large files written by a thread from gathered buffers "
                              "(`jaxrobo.io.npz.UncachedWrites`) against the code before, alternating; the disk's "
                              "own write rates; a prototype starting the statistics earlier, not adopted",
    "goto_compile_options_s36.json": "QuadcopterGoto-v2's cold compile on a timeline (JAX's and XLA's logs) and "
                                     "XLA compile options tried on it, none adopted",
    "uneven_tables_s36.json": "A 1 M-env run whose tables are not whole blocks of the device deflate (device memory "
                              "peak, the file's CRCs), and XLA's parallel LLVM compile option, which this jaxlib "
                              "refuses",
    "moment_blocks_s34.json": "A 1 M-env run's writing with the statistics' means and spreads summed over blocks of "
                              "1 MB (before) or 8 MB of envs (adopted), alternating, with timelines",
    "goto_compile_s33.json": "Where QuadcopterGoto-v2's cold compile goes (JAX's events and XLA's timers), its step "
                             "alone with and without the task kernel and with parts of the kernel stubbed, and a "
                             "prototype tracing the kernel once",
    "arm_analytic.json": "ArmReach-v0's default command on 2 CPU cores before (MJX) and after (its closed form), "
                         "farm-bench alternating, and the closed form's default on 16 seeds",
    "time_to_trained_check_s31.json": "Every task's default command cold and warm (seeds 0-2) and the 65,536-env "
                                      "step-budget run, re-measured at 8f291fa on another H200 host",
    "time_to_trained_check.json": "The tabular default commands cold and warm after this session's writing changes "
                                  "(a check beside the README's table, another host)",
    "time_to_trained_065bc26.json": "Time to a trained robot re-checked at 065bc26 on another H200 host "
                                    "(`benchmarks/time_to_trained.py --seeds 3`), beside the README's table",
    "time_to_trained_5b0c43b.json": "Time to a trained robot re-checked at 5b0c43b on a third H200 host "
                                    "(`benchmarks/time_to_trained.py --seeds 3`), beside the README's table",
    "time_to_trained_5784dc9.json": "Time to a trained robot re-checked at 5784dc9 on a fourth H200 host "
                                    "(`benchmarks/time_to_trained.py --seeds 3`), beside the README's table",
    "time_to_trained_peers.json": "CartPoleContinuous-v0's default command beside Brax's PPO on Brax's own "
                                  "inverted_pendulum with its notebook's settings (`benchmarks/time_to_trained.py "
                                  "--peers`), one call",
    "compile_beside_cpu.json": "ExecutionPlan.compile_beside on 2 CPU cores, measured again: each tabular "
                               "task's first and warm runs with it on and off (left off)",
    "chunk_collectives.json": "What a training chunk split over 4 devices exchanges at every step "
                              "(`benchmarks/studies/chunk_collectives.py`), and the cart-pole's run in one process "
                              "and in two",
    "compile_flags_not_adopted.json": "ArmReach-v0's first-use compile on 2 CPU cores, and two XLA flags tried on "
                                      "it: measured, not adopted",
    "levers_not_adopted.json": "Start-up with JAX's backend started in a thread, and a cold compile under four XLA "
                               "flags: measured, not adopted",
    "compile_order.json": "The tabular default commands cold and warm before and after the chunk is traced first "
                          "and the small programs (bounds, keys, tables picked) are built on the host or compiled "
                          "ahead, alternating in one call",
    "large_runs_check.json": "The 65,536- and 1,048,576-env cart-pole runs under a step budget, cold and warm, after "
                             "this session's compile order (one call)",
    "quick_exit.json": "The default commands warm before and after the command's exit skips the interpreter's "
                       "teardown (`jaxrobo.core.quick_exit`), alternating in one call; the 65,536-env run after it",
    "scale_train_kernel_2gpu.json": "`jaxrobo train` of the analytic cart-pole on 1 and 2 GPUs under the automatic "
                                    "plan (the whole-chunk kernel on each GPU's envs): the same tables and records "
                                    "(the run is too short to time)",
    "before.json": "The cart-pole chunk kernel's row before its move to `envs/cartpole/kernel.py` (same call as "
                   "`after.json`)",
    "after.json": "The cart-pole chunk kernel's row after its move to `envs/cartpole/kernel.py` (same call as "
                  "`before.json`)",
    "summary.json": "A sweep's own summary (`bash benchmarks/multiprocess_demo.sh`)",
}
#: Row fields that identify a machine state or a checksum rather than a figure a reader compares.
NOISE = {"execution_plan", "plan", "digests", "q_checksum", "checksum", "device_bytes_in_use",
         "device_peak_bytes_in_use",
         "device_bytes_limit", "part", "cache_dir", "python_start_s", "first_chunk_at", "argv", "command",
         "q_fingerprint_after_one_chunk", "last_returns", "sps_per_epoch", "seeds", "env_state_bytes", "n_states",
         "qtable_bytes", "platform", "reason", "x_sim", "sim_seconds_per_s", "control_dt", "opts"}
MAX_COLUMNS = 11


def fmt(key: str, value: Any) -> str:
    """One cell: rates in k/M/G, shares as given, other floats to 3 significant digits, ints with commas."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if "per_s" in key or key.endswith("_per_second") or key.startswith("steps_per_second"):
            return throughput._fmt_rate(value)
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        return f"{value:.3g}"
    if isinstance(value, (list, tuple)):
        nums = [v for v in value if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if nums and len(nums) == len(value) and len(value) > 4:
            return f"{len(nums)} values, median {statistics.median(nums):.3g}, min {min(nums):.3g}"
        return ", ".join(fmt(key, v) for v in value)
    text = str(value).replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= 80 else text[:77] + "..."


def _scalar(v: Any) -> bool:
    return v is None or isinstance(v, (bool, int, float, str))


#: The columns of a ``benchmarks/scale_out.py`` file's table.
SCALE_COLUMNS = ["gpus", "processes", "status", "wall_s", "compile_s", "run_s", "steps_per_s_run", "efficiency_run",
                 "efficiency_wall", "checksum", "same_as_baseline"]


def rows_table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> list[str]:
    """A markdown table of ``rows``: the given columns, else the scalar fields most rows have, in first-seen order."""
    if columns is None:
        seen: dict[str, int] = {}
        for r in rows:
            for k, v in r.items():
                if k not in NOISE and (_scalar(v) or isinstance(v, list) and len(v) > 4):
                    seen[k] = seen.get(k, 0) + 1
        columns = [k for k, c in seen.items() if c * 2 >= len(rows)][:MAX_COLUMNS]
    out = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        out.append("| " + " | ".join(fmt(k, r.get(k)) for k in columns) + " |")
    return out


def flat_figures(data: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``(key, value)`` of a result's top-level figures; small dicts are flattened one level
    (``fresh_success.median``)."""
    out = []
    for k, v in data.items():
        if k in NOISE or k in ("rows", "parts", "meta", "config", "settings", "overrides", "note", "what"):
            continue
        if k == "runs" and not isinstance(v, int):
            continue
        if isinstance(v, dict) and all(_scalar(x) for x in v.values()) and prefix == "":
            out += [(f"{k}.{kk}", vv) for kk, vv in v.items()]
        elif _scalar(v) or isinstance(v, list) and all(_scalar(x) for x in v):
            out.append((prefix + k, v))
    return out


def throughput_rows(data: dict[str, Any]) -> list[str]:
    """The throughput rows with the ratios ``benchmarks/throughput.py`` computes (per env step against the fastest
    peer of the family at the same n_envs; against Brax; against the seed-style loop)."""
    rows = [dict(r) for r in data["rows"]]
    throughput._ratios(rows)
    out = ["| suite | env | backend | mode | n_envs | env steps/s | physics steps/s | compile s | x peer | x brax "
           "| x seed loop |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        status = r.get("status")
        if status not in ("ok", "published"):
            continue
        rate = r.get("steps_per_s")
        if r["suite"] == "jaxrobo-cli":
            rate_cell = f"{throughput._fmt_rate(rate)} useful ({(r.get('useful_share') or 0):.0%} of slots, " \
                        f"{r.get('wall_s', 0):.0f} s wall)"
        else:
            rate_cell = throughput._fmt_rate(rate) if status == "ok" else "published: " + fmt("reason", r.get("reason"))
        out.append("| " + " | ".join([
            r["suite"], r["env"], str(r.get("backend", "")), str(r.get("mode", "")), fmt("n_envs", r.get("n_envs")),
            rate_cell, throughput._fmt_rate(r.get("physics_steps_per_s")),
            fmt("compile_s", r.get("compile_s")), throughput._fmt_x(r.get("x_env")), throughput._fmt_x(r.get("x_brax")),
            throughput._fmt_x(r.get("x_seed_loop"))]) + " |")
    out.append("")
    out.append("x peer: env steps/s over the fastest measured peer of the same family (cart-pole, quadcopter) at "
               "the same n_envs; x brax: over Brax `inverted_pendulum` on MJX at the same n_envs; x seed loop: over "
               "the dict-based tabular loop of the original tutorial. Published rows are a peer's own figure on its "
               "own machine, never in a ratio.")
    return out


def recorded(data: Any, key: str) -> Any:
    """A field a result records about its run, from its ``meta`` or its top level (None for a bare list)."""
    if not isinstance(data, dict):
        return None
    meta = data.get("meta") if isinstance(data.get("meta"), dict) else {}
    return meta.get(key) or data.get(key)


def device_of(data: Any) -> str | None:
    """The device a result names (``meta.device`` or ``device``), with its JAX version where recorded."""
    dev, jax_version, cores = recorded(data, "device"), recorded(data, "jax"), recorded(data, "cpu_count")
    if dev == "cpu" and cores:
        dev = f"cpu ({cores} cores)"
    if dev and jax_version and "jax" not in str(dev):
        return f"{dev}, jax {jax_version}"
    return dev


def command_of(data: Any) -> str | None:
    """The command that measured a result: its ``argv`` joined, or its recorded ``command``."""
    argv = recorded(data, "argv")
    if isinstance(argv, list) and argv:
        return " ".join(str(a) for a in argv)
    return recorded(data, "command")


def section(path: str, data: Any) -> list[str]:
    """The markdown of one result file."""
    rel = os.path.relpath(path, ROOT)
    name = os.path.basename(path)
    title = WHAT.get(name)
    if title is None and name.startswith("goto_learning_"):
        title = f"{name[len('goto_learning_'):].split('_')[0].removesuffix('.json')} learning over independent runs " \
                "(`benchmarks/goto_learning.py`)"
    if title is None and name.startswith("arm_learning_"):
        title = "ArmReach-v0 learning over independent runs (`benchmarks/arm_learning.py`)"
    if title is None and name.startswith("learning_targets"):
        title = "Budgets that meet each task's learning target (`benchmarks/learning_targets.py`)"
    if title is None and "/goto_randomised/" in rel:
        title = "QuadcopterGoto-v2 trained under a randomisation schedule (`benchmarks/goto_learning.py --set ...`)"
    out = [f"### {title or name}", "", f"- file: `{rel}`"]
    dev, cmd = device_of(data), command_of(data)
    if dev:
        out.append(f"- device: {dev}")
    if cmd:
        out.append(f"- command: `{cmd}`")
    if isinstance(data, dict) and (data.get("note") or data.get("what")):
        out.append(f"- note: {str(data.get('note') or data.get('what'))}")
    out.append("")
    if isinstance(data, dict) and isinstance(data.get("meta"), dict) and data["meta"].get("parts"):
        out.append("Merged from " + str(len(data["meta"]["parts"])) + " runs: " + "; ".join(
            "`" + " ".join(map(str, p.get("argv", []))) + "`" for p in data["meta"]["parts"]))
        out.append("")
    if isinstance(data, dict) and isinstance(data.get("rows"), list) and data["rows"] and "suite" in data["rows"][0]:
        return out + throughput_rows(data) + [""]
    if isinstance(data, dict) and isinstance(data.get("rows"), list) and data["rows"] \
            and "same_as_baseline" in data["rows"][0]:  # scale_out.py: the speed-up and whether the bytes agree
        return out + rows_table(data["rows"], SCALE_COLUMNS) + [""]
    if name == "time_to_trained.json" and isinstance(data, dict):
        return out + time_to_trained_table(data) + [""] + rows_table(data.get("rows", [])) + [""]
    if name == PEERS and isinstance(data, dict):
        return out + rows_table(data.get("rows", []), PEER_COLUMNS) + [""]
    if name == "ros_sim2sim.json" and isinstance(data, dict):  # its rows of three kinds, a table each
        for kind, columns in ROS_SIM2SIM_COLUMNS.items():
            rows = [r for r in data.get("rows", []) if r.get("kind") == kind]
            if rows:
                out += rows_table(rows, columns) + [""]
        return out
    if isinstance(data, list) and data and isinstance(data[0], dict):
        return out + rows_table(data) + [""]
    figures = flat_figures(data) if isinstance(data, dict) else []
    if figures:
        out += ["| figure | value |", "|---|---|"] + [f"| {k} | {fmt(k, v)} |" for k, v in figures] + [""]
    for key in ("rows", "runs", "parts"):
        block = data.get(key) if isinstance(data, dict) else None
        if isinstance(block, list) and block and all(isinstance(b, dict) for b in block):
            if all(isinstance(b.get("rows"), list) for b in block):  # runs/parts of a study: each its own table
                for b in block:
                    out += [f"`{fmt('command', b.get('command') or ' '.join(map(str, b.get('argv') or [])))}`", ""]
                    out += rows_table(b["rows"]) + [""]
            else:
                out += rows_table(block) + [""]
        elif isinstance(block, dict) and all(isinstance(b, dict) for b in block.values()):
            out += rows_table([{"run": k, **v} for k, v in block.items()]) + [""]
    if isinstance(data, dict) and isinstance(data.get("ablations_1m"), list):
        out += rows_table(data["ablations_1m"]) + [""]
    return out


#: The measured peer beside the headline (:func:`peers_sentence`), in the same device's folder.
PEERS = "time_to_trained_peers.json"
PEER_COLUMNS = ["env_id", "agent", "cache", "seed", "wall_seconds", "startup_seconds", "run_seconds",
                "evaluation_seconds", "env_steps", "learning_value", "target_met_at_steps", "target_met_at_seconds"]
#: ``benchmarks/ros_sim2sim.py``'s rows, by kind: the columns of each kind's table.
ROS_SIM2SIM_COLUMNS = {
    "train": ["run", "command", "exit_code", "wall_seconds", "env_steps", "eval_success_rate", "eval_mean_length"],
    "sim2sim": ["page", "env_id", "episodes", "seed", "same_outcome", "identical_flights", "median_part_step",
                "native_success_rate", "jax_export_success_rate", "jax_evaluation_success_rate", "native_mean_length",
                "jax_export_mean_length", "runner_on_jax_obs", "max_obs_gap_at_step_1", "max_obs_gap_at_step_50",
                "max_obs_gap_before_parting"],
    "ros": ["name", "episodes", "seed", "mode", "status", "success_rate", "mean_steps", "same_outcome_as_native",
            "same_steps_as_native", "same_steps_as_jax_export", "native_success_rate_same_episodes",
            "jax_export_success_rate_same_episodes", "jax_evaluation_success_rate_same_episodes", "wall_seconds",
            "reason"],
}
#: The README's headline block, filled from this device's time_to_trained.json (:func:`readme_block`).
README = os.path.join(ROOT, "README.md")
HEADLINE_DEVICE = "h200"
BEGIN, END = "<!-- time-to-trained: generated by benchmarks/results_page.py -->", "<!-- end of time-to-trained -->"


def time_to_trained_table(data: dict[str, Any]) -> list[str]:
    """One row per task of a time_to_trained.json: the default command's wall with an empty and a warm compile
    cache, the warm wall's split, the env steps it took, its learning figure, and over the recorded seeds the
    worst and median figure."""
    rows = [r for r in data.get("rows", []) if "error" not in r]
    seeds = (data.get("seeds") or {}).get("runs") or {}
    out = ["| task (learner) | wall, empty cache | wall, warm cache | warm: start-up / compile / run / eval / write / "
           "exit | env steps | learned (target) | seeds: worst / median |", "|---|---|---|---|---|---|---|"]
    for env_id in dict.fromkeys(r["env_id"] for r in rows):
        cold = next((r for r in rows if r["env_id"] == env_id and r["cache"] == "cold"), None)
        warm = next((r for r in rows if r["env_id"] == env_id and r["cache"] == "warm"), None)
        if warm is None:
            continue
        # A run that does not measure its start-up (ppo) has it in the rest: shown as one "start-up + exit" figure.
        rest = warm.get("rest_seconds", warm.get("startup_and_rest_seconds"))
        startup = warm.get("startup_seconds")
        parts = [warm.get("compile_seconds"), warm.get("run_seconds"), warm.get("evaluation_seconds"),
                 warm.get("writing_seconds")]
        split = " / ".join("-" if v is None else f"{v:.1f}" for v in parts)
        split = (f"{startup:.1f} / {split} / {rest:.1f}" if startup is not None
                 else f"({rest:.1f} with the exit) / {split} / -" if rest is not None else f"- / {split} / -")
        figure = warm["learning_value"]
        target = str(warm.get("learning_target") or "").split(" (")[0]
        learned = f"{figure:.4g} ({target})" if target else f"{figure:.4g}"
        runs = seeds.get(env_id) or []
        spread = "-"
        if runs:
            values = [float(r["figure"]) for r in runs]
            spread = f"{min(values):.4g} / {statistics.median(values):.4g} ({len(values)} seeds)"
        empty = "-" if cold is None else f"{cold['wall_seconds']:.1f} s"
        out.append(f"| {env_id} ({warm['agent'].replace('preset', 'qlearn')}) | {empty} | "
                   f"{warm['wall_seconds']:.1f} s | {split} | {warm['env_steps']:,} | {learned} | {spread} |")
    return out


def readme_block() -> str | None:
    """The README's time-to-trained table, from ``benchmarks/results/<HEADLINE_DEVICE>/time_to_trained.json``."""
    path = os.path.join(RESULTS, HEADLINE_DEVICE, "time_to_trained.json")
    if not os.path.exists(path):
        return None
    with open(path, encoding="utf-8") as f:
        data = json.load(f)
    anchors = "; ".join(f"{a['what']}: {'under ' if a.get('at_most') else ''}{a['seconds']:.0f} s on {a['hardware']}"
                        for a in data.get("anchors", []) if a.get("seconds") is not None)
    lines = [BEGIN, f"`jaxrobo train --env ID` with no other flag, start to exit, on one {data['device']}: it "
             "trains until the task's learning target holds on fresh greedy episodes, then evaluates and writes the "
             "run (seconds; a ppo run's compile is inside its run; [docs/results.md](docs/results.md) has every "
             "figure, `benchmarks/time_to_trained.py` measures them)." + (f" For comparison, {anchors}." if anchors
                                                                         else "") + peers_sentence(), ""] \
        + time_to_trained_table(data) + ["", END]
    return "\n".join(lines)


def peers_sentence() -> str:
    """The README's measured peer, from ``time_to_trained_peers.json`` (``time_to_trained.py --peers``): Brax's
    own cart-pole beside CartPoleContinuous-v0's command, in one call on one device; empty where it is absent."""
    path = os.path.join(RESULTS, HEADLINE_DEVICE, PEERS)
    if not os.path.exists(path):
        return ""
    with open(path, encoding="utf-8") as f:
        data = json.load(f)
    rows = [r for r in data.get("rows", []) if r.get("exit_code") == 0]
    device = str(data.get("device", "device")).split(" (")[0]

    def walls(env_id: str, cache: str, key: str = "wall_seconds") -> str:
        got = sorted(r[key] for r in rows if r["env_id"] == env_id and r["cache"] == cache and r.get(key))
        if not got:
            return "-"
        low, high = f"{got[0]:.1f}", f"{got[-1]:.1f}"
        return low if low == high else f"{low}-{high}"

    peer, ours = "brax:inverted_pendulum", "CartPoleContinuous-v0"
    if not any(r["env_id"] == peer for r in rows) or not any(r["env_id"] == ours for r in rows):
        return ""
    return (f" Measured in one call on one {device} ([{PEERS}](docs/results.md)): Brax's PPO on Brax's own cart-pole "
            f"(`inverted_pendulum`, the settings of Brax's training notebook) takes {walls(peer, 'cold')} s with an "
            f"empty cache and {walls(peer, 'warm')} s warm from start to exit, its evaluation first at the target's "
            f"return after {walls(peer, 'warm', 'target_met_at_seconds')} s warm; {ours}'s command "
            f"{walls(ours, 'cold')} s and {walls(ours, 'warm')} s.")


def with_readme_block(readme: str, block: str) -> str:
    """``readme`` with the text between :data:`BEGIN` and :data:`END` (both kept) replaced by ``block``."""
    start, end = readme.find(BEGIN), readme.find(END)
    if start < 0 or end < start:
        raise SystemExit(f"{README}: no {BEGIN} ... {END} block to fill")
    return readme[:start] + block + readme[end + len(END):]


def is_learning(data: Any) -> bool:
    """A learning-over-runs result (``goto_learning.py``, ``arm_learning.py``): one success rate per run."""
    return isinstance(data, dict) and ("fresh_success" in data or "success_per_run" in data)


def learning_table(datas: list[tuple[str, Any]]) -> list[str]:
    """One row per learning result of a device: the share of fresh greedy episodes that reach the goal, over runs
    that differ only in their seed."""
    out = ["### Learning over independent runs (`benchmarks/goto_learning.py`, `benchmarks/arm_learning.py`)", "",
           "Each run trains from its own seed with the task's preset, then flies fresh greedy episodes; success = "
           "the share that reach the goal (the learning target is 0.8).", "",
           "| file | env | runs | n_envs | episodes per env | train s | median | mean | worst | runs ≥ 0.8 |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for path, d in datas:
        if "fresh_success" in d and isinstance(d["fresh_success"], dict):
            f = d["fresh_success"]
            med, mean, low, share = f.get("median"), f.get("mean"), f.get("min"), f.get("share_of_runs_at_target")
        else:
            per = d.get("success_per_run") or d.get("selection_success_per_run") or []
            med = d.get("median_success", statistics.median(per) if per else None)
            mean = statistics.fmean(per) if per else None
            low = d.get("min_success", min(per) if per else None)
            share = sum(x >= 0.8 for x in per) / len(per) if per else None
        out.append("| " + " | ".join([
            f"`{os.path.relpath(path, RESULTS)}`", str(d.get("env", "QuadcopterGoto-v1")), fmt("runs", d.get("runs")),
            fmt("n_envs", d.get("n_envs")), fmt("nepisodes", d.get("nepisodes")),
            fmt("train_seconds", d.get("train_seconds")), fmt("median", med), fmt("mean", mean), fmt("min", low),
            "-" if share is None else f"{share:.0%}"]) + " |")
    return out + [""]


def result_files() -> dict[str, list[str]]:
    """``{device folder: [JSON paths]}``, the main job's file first, then by path."""
    found: dict[str, list[str]] = {}
    for device in sorted(os.listdir(RESULTS)):
        folder = os.path.join(RESULTS, device)
        if device == "local" or not os.path.isdir(folder):
            continue
        paths = [os.path.join(d, f) for d, _, files in os.walk(folder) for f in files if f.endswith(".json")]
        found[device] = sorted(paths, key=lambda p: (os.path.basename(p) != "throughput.json", p))
    return found


def page() -> str:
    lines = ["# Results", "",
             "Every figure jaxrobo reports, per device, generated by `python benchmarks/results_page.py` from the "
             "benchmark JSON under `benchmarks/results/<device>/` (do not edit by hand). How to run each benchmark and "
             "what it measures: [benchmarks.md](benchmarks.md).", ""]
    files = result_files()
    lines += ["Devices: " + ", ".join(f"[{d}](#{d})" for d in files), ""]
    for device, paths in files.items():
        datas = []
        for p in paths:
            with open(p, encoding="utf-8") as f:
                datas.append((p, json.load(f)))
        named = next((device_of(d) for _, d in datas if device_of(d)), device)
        lines += [f"## {device}", "", f"Device: {named}.", ""]
        figures = sorted(f for f in os.listdir(os.path.join(RESULTS, device)) if f.endswith(".png"))
        for fig in figures:
            lines += [f"![{fig}](../benchmarks/results/{device}/{fig})", ""]
        learning = [(p, d) for p, d in datas if is_learning(d)]
        for p, data in datas:
            if not is_learning(data):
                lines += section(p, data)
        if learning:
            lines += learning_table(learning)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=PAGE, help="the page to write (default docs/results.md)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if the page differs")
    args = ap.parse_args(argv)
    text = page()
    block = readme_block()
    with open(README, encoding="utf-8") as f:
        readme = f.read()
    new_readme = readme if block is None else with_readme_block(readme, block)
    if args.check:
        with open(args.out, encoding="utf-8") as f:
            same = f.read() == text
        same_readme = new_readme == readme
        print(f"{args.out}: {'up to date' if same else 'stale: run python benchmarks/results_page.py'}")
        print(f"{README}: {'up to date' if same_readme else 'stale: run python benchmarks/results_page.py'}")
        return 0 if same and same_readme else 1
    with open(args.out, "w", encoding="utf-8") as f:
        f.write(text)
    if new_readme != readme:
        with open(README, "w", encoding="utf-8") as f:
            f.write(new_readme)
    print(f"wrote {args.out} ({len(text.splitlines())} lines) and the README's time-to-trained table")
    return 0


if __name__ == "__main__":
    sys.exit(main())
