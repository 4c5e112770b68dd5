"""Simulators: the seed's Gazebo layer. :mod:`~jaxrobo.physics.sim` advances a MuJoCo model one control step on
MJX, Brax's pipelines or a robot's hand-written closed form. Beside it, what changes how a step compiles and never
what it computes, read while the step is traced: :mod:`~jaxrobo.physics.mjx_lean` (one MJX stage in a form XLA
compiles better, version-guarded), :mod:`~jaxrobo.physics.fused` (the trace-time switches the execution plan sets
for simulators and tasks) and :mod:`~jaxrobo.physics.libdevice_sincos` (libdevice's sin/cos written out for Pallas
kernels, version-guarded)."""
