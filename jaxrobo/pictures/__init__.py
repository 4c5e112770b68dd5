"""Pictures: MuJoCo's offscreen frames and videos (:mod:`~jaxrobo.pictures.render`), reward curves
(:mod:`~jaxrobo.pictures.plots`); the ``jaxrobo show`` command (:mod:`jaxrobo.show`) draws flights with them."""
