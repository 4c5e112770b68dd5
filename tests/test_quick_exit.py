"""The ``jaxrobo`` command's exit without the interpreter's teardown (:mod:`jaxrobo.core.quick_exit`): what Python's
own exit does that can matter still happens (threads awaited, ``atexit`` handlers run, streams flushed, the exit
code kept), and a traced or profiled process keeps Python's exit. Each case is a fresh process."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}


def python(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=ENV, cwd=ROOT,
                          timeout=timeout)


def test_the_private_function_it_relies_on_runs_every_handler_once_and_clears_them():
    code = ("import atexit; seen = []; atexit.register(seen.append, 1); atexit.register(seen.append, 2); "
            "atexit._run_exitfuncs(); print(seen, atexit._ncallbacks())")
    out = python("-c", code)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[0] == "[2, 1] 0"  # last registered first, as at a normal exit


def test_threads_handlers_streams_and_the_code_survive_the_quick_exit(tmp_path):
    mark, handler = tmp_path / "thread", tmp_path / "handler"
    code = (
        "import atexit, sys, threading, time\n"
        "from jaxrobo.core.quick_exit import available, exit_process\n"
        f"atexit.register(lambda: open({str(handler)!r}, 'w').write('ran'))\n"
        f"t = threading.Thread(target=lambda: (time.sleep(0.5), open({str(mark)!r}, 'w').write('done')))\n"
        "t.start()\n"
        "sys.stdout.write('x' * 200000)\n"  # buffered: a pipe's reader gets it all
        "sys.stderr.write(f'available={available()}')\n"
        "exit_process(3)\n"
        "print('not reached')\n")
    out = python("-c", code)
    assert out.returncode == 3
    assert out.stdout == "x" * 200000
    assert out.stderr == "available=True"
    assert mark.read_text() == "done" and handler.read_text() == "ran"


def test_the_command_exits_quickly_with_its_code_and_its_whole_output(tmp_path):
    handler = tmp_path / "handler"
    code = ("import atexit, runpy, sys\n"
            f"atexit.register(lambda: open({str(handler)!r}, 'w').write('ran'))\n"
            "sys.argv = ['jaxrobo'] + sys.argv[1:]\n"
            "runpy.run_module('jaxrobo.cli', run_name='__main__')\n")
    listed = python("-c", code, "list")
    assert listed.returncode == 0, listed.stderr
    assert "CartPoleStayUp-v0" in listed.stdout and handler.read_text() == "ran"
    refused = python("-m", "jaxrobo.cli", "train", "--env", "NoSuchEnv-v0")
    assert refused.returncode == 2
    assert refused.stderr.startswith("jaxrobo train:") and len(refused.stderr.strip().splitlines()) == 1


def test_a_profiled_command_keeps_pythons_exit_so_the_profile_is_written(tmp_path):
    prof = tmp_path / "list.prof"
    out = python("-m", "cProfile", "-o", str(prof), "-m", "jaxrobo.cli", "list")
    assert out.returncode == 0, out.stderr
    assert prof.stat().st_size > 0
    traced = python("-c", "import sys; sys.settrace(lambda *a: None); "
                          "from jaxrobo.core.quick_exit import available; print(available())")
    assert traced.stdout.strip() == "False"


def test_outside_the_checked_versions_the_exit_is_pythons_own(monkeypatch):
    from jaxrobo.core import quick_exit

    monkeypatch.setattr(sys, "version_info", (quick_exit.CHECKED[1][0], quick_exit.CHECKED[1][1] + 1, 0))
    assert not quick_exit.available()
    with pytest.raises(SystemExit) as raised:  # sys.exit, not os._exit: this test process goes on
        quick_exit.exit_process(4)
    assert raised.value.code == 4
