"""benchmarks/randomisation_cost.py with every AOT compile given XLA's ptxas flags from $PTXAS_FLAGS
(compiler_options xla_gpu_ptx_compiler_extra_flags, e.g. --maxrregcount=96)."""
import os
import runpy
import sys

args = sys.argv[1:]
if "--device" in args:
    at = args.index("--device")
    os.environ["JAX_PLATFORMS"] = {"cpu": "cpu", "gpu": "cuda"}[args[at + 1]]
    del args[at:at + 2]
sys.path.insert(0, "benchmarks")
import jax.stages as stages  # noqa: E402

flags = os.environ.get("PTXAS_FLAGS", "")
_compile = stages.Lowered.compile


def compile_(self, compiler_options=None, **kw):
    opts = dict(compiler_options or {})
    if flags:
        opts["xla_gpu_ptx_compiler_extra_flags"] = flags
    return _compile(self, compiler_options=opts, **kw)


stages.Lowered.compile = compile_
sys.argv = ["benchmarks/randomisation_cost.py"] + args
runpy.run_path("benchmarks/randomisation_cost.py", run_name="__main__")
