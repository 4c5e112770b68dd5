"""Speed choices: everything that changes how fast a run goes and never what it computes.
:mod:`~jaxrobo.speed.plan` (the one ``ExecutionPlan``, passed explicitly and printed), an env's reset and step compiled
once (:mod:`~jaxrobo.speed.compiled`), JAX's persistent compilation cache (:mod:`~jaxrobo.speed.cache`), the traced
programs kept beside it (:mod:`~jaxrobo.speed.reuse`), sharding over devices and processes
(:mod:`~jaxrobo.speed.sharding`), large arrays' copies to the host through page-locked memory
(:mod:`~jaxrobo.speed.locked_copy`) and large mostly-zero arrays deflated on the device for their file
(:mod:`~jaxrobo.speed.device_deflate`). The robots' and tasks' own kernels live with them
(``envs/quadcopter/kernel.py``, ``envs/quadcopter/goto_kernel.py``, the cart-pole's whole-chunk
``envs/cartpole/kernel.py``)."""
