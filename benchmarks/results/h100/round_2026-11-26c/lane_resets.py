"""benchmarks/randomisation_cost.py with the cart-pole kernel's randomised resets hashed lane by lane, as before
the groups of four hashed the draws (GROUP_RESETS off; the nominal kernel then hashes lane by lane too).
Same arguments; --device gpu is taken here (JAX is imported to set the knob before the benchmark runs)."""
import os
import runpy
import sys

args = sys.argv[1:]
if "--device" in args:
    at = args.index("--device")
    os.environ["JAX_PLATFORMS"] = {"cpu": "cpu", "gpu": "cuda"}[args[at + 1]]
    del args[at:at + 2]
sys.path.insert(0, "benchmarks")
from jaxrobo.speed import fused_pallas  # noqa: E402

fused_pallas.GROUP_RESETS = False
sys.argv = ["benchmarks/randomisation_cost.py"] + args
runpy.run_path("benchmarks/randomisation_cost.py", run_name="__main__")
