"""Run every command of the README's "Quickstart" section and the quickstart notebook, as a newcomer would, and write
a transcript with each command's wall time, exit code and last lines of output.

    python scripts/readme_transcript.py --out docs/transcripts/cpu-2cores.md          # in a fresh clone
    python scripts/readme_transcript.py --device gpu --out docs/transcripts/h100.md

The commands are read from the README itself (the ``bash`` and ``python`` blocks of "## Quickstart", up to the
next ``## `` heading), so the transcript cannot drift from what the README says; they run one after the other in the
checkout this script belongs to, in order (later commands read the runs earlier ones wrote). A line that cannot
run unattended (``...`` placeholders, a Ctrl-C) is listed as skipped, with why. ``--device gpu`` sets
``JAX_PLATFORMS=cuda`` for every command. The README's outputs land in ``runs/`` (git-ignored); this script
removes ``runs/`` and ``policy/`` first (``--keep`` leaves them), and gives the commands an empty compile cache of
their own (``JAXROBO_CACHE_DIR``, a temporary folder; ``--cache DIR`` names one), so every command starts as on a
fresh clone: the first to compile a program pays for it, later ones find it in the cache.
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Lines of the README that need a person at the keyboard or stand for "your own arguments".
UNATTENDED = ((re.compile(r"\.\.\."), "a placeholder (`...`), not a command"),
              (re.compile(r"Ctrl-C"), "needs a Ctrl-C by hand (tests/test_resume.py does it by signal)"),
              (re.compile(r"GPU-sized"), "sized for a GPU (its CPU time is in its comment)"))
#: Of those, the ones that run unattended on a GPU.
GPU_RUNS = ("GPU-sized",)


def readme_commands(path: str) -> list[tuple[str, str]]:
    """``(kind, text)`` for each command of the README's "Quickstart" section: ``bash`` lines and whole ``python``
    blocks, in order."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    start = text.index("\n## Quickstart")
    end = text.find("\n## ", start + 1)
    end = len(text) if end < 0 else end
    out = []
    for lang, body in re.findall(r"```(bash|python)\n(.*?)```", text[start:end], flags=re.S):
        if lang == "python":
            out.append(("python", body))
            continue
        out.extend(("bash", line.strip()) for line in body.splitlines() if line.strip())
    return out


def run(kind: str, text: str, env: dict, timeout: float) -> dict:
    argv = ["bash", "-c", text] if kind == "bash" else [sys.executable, "-c", text]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        rc, output = p.returncode, (p.stdout + p.stderr)
    except subprocess.TimeoutExpired as err:
        rc = "timeout"
        output = (err.stdout or b"").decode(errors="replace") if isinstance(err.stdout, bytes) else (err.stdout or "")
    return {"rc": rc, "seconds": time.perf_counter() - t0, "tail": output.strip().splitlines()[-4:]}


def notebook(env: dict, timeout: float) -> dict:
    """The quickstart notebook top to bottom in a fresh kernel (nbclient, as tests/test_notebook.py runs it)."""
    code = ("import nbformat, nbclient; nb = nbformat.read('notebooks/quickstart.ipynb', as_version=4); "
            "nbclient.NotebookClient(nb, timeout=600, kernel_name='python3', "
            "resources={'metadata': {'path': '.'}}).execute(); "
            "outs = [o for c in nb.cells if c.cell_type == 'code' for o in c.get('outputs', [])]; "
            "print(len(outs), 'outputs,', sum('image/png' in o.get('data', {}) for o in outs), 'PNG images,', "
            "sum(o.get('output_type') == 'error' for o in outs), 'errors')")
    return run("python", code, env, timeout)


def machine(env: dict) -> tuple[str, str]:
    """``(device kind, jax version)``, asked of a child process: jax in this one would hold the GPU's memory."""
    code = "import jax; print(jax.devices()[0].device_kind); print(jax.__version__)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True).stdout.split("\n")
    return (out[0], out[1]) if len(out) > 1 else ("unknown device", "unknown")


def write(args, rows: list[dict], kind: str, version: str) -> None:
    """The transcript of the rows so far (written after every command, so a stopped transcript keeps its rows)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    commit = commit.stdout.strip()
    head = [f"# README transcript: {kind} ({os.cpu_count()} cores visible)", "",
            f"`python scripts/readme_transcript.py --device {args.device} --out {os.path.relpath(args.out, ROOT)}` on "
            f"{time.strftime('%Y-%m-%d')}, "
            f"Python {platform.python_version()}, jax {version}, commit "
            f"{commit}. "
            "Each command ran in order in one checkout, as the README gives it; times are wall seconds from start to "
            f"exit (compile included; {args.cache_said}).", "",
            "| # | command | wall (s) | exit | last lines of output |", "|---|---|---|---|---|"]
    esc = lambda s: s.replace("|", "\\|").replace("\n", " ")  # noqa: E731
    for i, r in enumerate(rows, 1):
        cmd = esc(r["text"] if r["kind"] != "python" else "python block: " + r["text"].strip().splitlines()[0] + " …")
        if "skipped" in r:
            head.append(f"| {i} | `{cmd}` | – | skipped | {esc(r['skipped'])} |")
        else:
            head.append(f"| {i} | `{cmd}` | {r['seconds']:.1f} | {r['rc']} | {esc(' ⏎ '.join(r['tail']))[:400]} |")
    total = sum(r.get("seconds", 0.0) for r in rows)
    head += ["", f"Total {total / 60:.1f} min; {sum(r.get('rc') not in (0, None) for r in rows if 'rc' in r)} "
             "command(s) failed."]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as f:
        f.write("\n".join(head) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="markdown transcript to write")
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed to one command")
    ap.add_argument("--only", default=None, help="run only the commands containing this text")
    ap.add_argument("--no-notebook", action="store_true")
    ap.add_argument("--keep", action="store_true", help="keep runs/ and policy/ from an earlier transcript")
    ap.add_argument("--start-at", default=None, metavar="TEXT",
                    help="skip the commands before the first one containing TEXT "
                         "(with --keep: go on with a transcript)")
    ap.add_argument("--cache", default=None, metavar="DIR",
                    help="the commands' compile cache (default: an empty temporary folder, removed at the end)")
    args = ap.parse_args(argv)
    if args.cache is None:
        cache = tempfile.mkdtemp(prefix="jaxrobo-transcript-cache-")
        args.cache_said = "the compile cache empty at the first command, then as the earlier commands left it"
    else:
        cache = args.cache
        args.cache_said = f"the compile cache {cache} as it was, then as the earlier commands left it"
    try:
        return transcript(args, cache)
    finally:
        if args.cache is None:
            shutil.rmtree(cache, ignore_errors=True)


def transcript(args, cache: str) -> int:
    if not args.keep:
        for d in ("runs", "policy"):
            shutil.rmtree(os.path.join(ROOT, d), ignore_errors=True)
    env = {**os.environ, "JAX_PLATFORMS": {"cpu": "cpu", "gpu": "cuda"}[args.device], "PYTHONUNBUFFERED": "1",
           "JAXROBO_CACHE_DIR": cache}
    bindir = os.path.dirname(sys.executable)  # the venv's `jaxrobo` before any other on PATH
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    info = machine(env)
    rows = []
    started = args.start_at is None
    for kind, text in readme_commands(os.path.join(ROOT, "README.md")):
        started = started or args.start_at in text
        if not started or (args.only and args.only not in text):
            continue
        why = next((w for pat, w in UNATTENDED if pat.search(text)
                    and not (args.device == "gpu" and pat.pattern in GPU_RUNS)), None)
        if why:
            rows.append({"kind": kind, "text": text, "skipped": why})
            print(f"skip  {text[:100]}  ({why})", flush=True)
            continue
        r = run(kind, text, env, args.timeout)
        rows.append({"kind": kind, "text": text, **r})
        print(f"{r['seconds']:7.1f} s  rc={r['rc']}  {text[:100]}", flush=True)
        write(args, rows, *info)
    if not args.no_notebook and not args.only:
        r = notebook(env, args.timeout)
        rows.append({"kind": "notebook", "text": "notebooks/quickstart.ipynb (nbclient, fresh kernel)", **r})
        print(f"{r['seconds']:7.1f} s  rc={r['rc']}  notebooks/quickstart.ipynb", flush=True)
    write(args, rows, *info)
    print(f"transcript: {args.out}")
    return 0 if all(r.get("rc", 0) == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
