"""The foundation every other part builds on, importing nothing else of jaxrobo's: frozen pytree dataclasses
with declared ranges (:mod:`~jaxrobo.core.struct`), counter-based random keys (:mod:`~jaxrobo.core.rng`; its hash
as jaxlib's GPU kernel where the execution plan says so, :mod:`~jaxrobo.core.hash_kernel`), action and observation
spaces (:mod:`~jaxrobo.core.spaces`), YAML configuration validated against those declarations
(:mod:`~jaxrobo.core.config`, :class:`~jaxrobo.core.config.ConfigError`), the refusal of 64-bit mode
(:mod:`~jaxrobo.core.precision`) and the package version (:mod:`~jaxrobo.core.version`)."""
