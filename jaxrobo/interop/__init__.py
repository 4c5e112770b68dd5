"""Other libraries' faces of a jaxrobo env: Gymnasium's single and vector envs
(:mod:`~jaxrobo.interop.gym_adapter`; their ids, registered without JAX on ``import jaxrobo``:
:mod:`~jaxrobo.interop.gym_ids`), Brax's ``Env`` (:mod:`~jaxrobo.interop.brax_env`) and the version-guarded
shims Brax needs (:mod:`~jaxrobo.interop.brax_compat`); and native MuJoCo's, one env on ``MjData`` without JAX
(:mod:`~jaxrobo.interop.native`, the base of the tasks' sim-to-sim ports)."""
