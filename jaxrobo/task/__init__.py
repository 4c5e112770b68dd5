"""The task API: the seed's task and robot layers as pure functions. :mod:`~jaxrobo.task.env` (``TaskEnv`` with
the seed's hooks, ``EnvState``, ``LearningTarget``), :mod:`~jaxrobo.task.robot`, :mod:`~jaxrobo.task.registry`
(ids, ``make``, ``register``, learners by name: the one place that reaches ``envs/`` and ``agents/``),
:mod:`~jaxrobo.task.autoreset` (the one autoreset), :mod:`~jaxrobo.task.wrappers` and
:mod:`~jaxrobo.task.rollout` (episodes of a policy, the one greedy tie rule). Task and robot authors import the
stable names of :mod:`jaxrobo.api`, not these modules."""
