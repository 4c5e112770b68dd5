"""Training: the trainer (:mod:`~jaxrobo.training.trainer`: ``TrainConfig``, the carry, the one jitted step),
the host driver (:mod:`~jaxrobo.training.driver`: chunks, progress, checkpoints, stop on a signal), the public
:func:`~jaxrobo.training.train.train`, the run's resolution from YAML and overrides
(:mod:`~jaxrobo.training.run`), its memory estimate (:mod:`~jaxrobo.training.budget`), checkpoints of the
carry (:mod:`~jaxrobo.training.checkpoint`), summaries (:mod:`~jaxrobo.training.summary`) and sweeps
(:mod:`jaxrobo.training.sweep`). Deep RL through Brax's trainers is :mod:`jaxrobo.deep`."""
