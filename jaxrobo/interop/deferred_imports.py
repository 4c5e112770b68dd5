"""Brax's envs and trainers without the imports they never use here: ``jaxopt`` and ``orbax.checkpoint`` load on
first use.

``import brax.envs`` imports every Brax env and, through them, the ``generalized`` pipeline, whose constraint
module imports ``jaxopt`` (which imports SciPy's optimizers) at its top; Brax's PPO and SAC trainers import their
checkpoint module, which imports ``orbax.checkpoint`` (through Flax's ``orbax_utils`` too). On 2 CPU cores
(``python -X importtime``) those two imports took 0.54 s and 0.29 s of every ``jaxrobo train --agent ppo|sac``
before its first compile. Neither is called by a jaxrobo run: JAXopt only by the ``generalized`` pipeline's
constraint solve (``jaxopt.ProjectedGradient``, as it traces its step), Orbax only by Brax's own
``save_checkpoint_path``/``checkpoint.load`` (jaxrobo keeps its own checkpoints, ``jaxrobo/deep/checkpoint.py``).
Both modules use them inside functions alone.

:func:`defer_brax_extras` puts a stand-in for each in ``sys.modules`` before Brax is imported (a
:class:`jaxrobo.core.deferred.Deferred`, as :mod:`jaxrobo.physics.mjx_import` uses): Brax binds the stand-in, and
the first attribute anything reads of it (a function call, ``from jaxopt import X``, a submodule import) imports
the real module, once, under a lock (trainers trace in threads), puts it in ``sys.modules`` and answers from it
from then on. A user's own ``import jaxopt`` afterwards gets the stand-in until it loads, then the module itself;
the stand-in forwards every attribute either way.

Guarded: only for the Brax versions of :data:`jaxrobo.interop.brax_compat.WRITTEN_FOR`, the range of every Brax
trick of jaxrobo (whose modules read both only inside functions), and only for a module that is installed and not
imported yet; elsewhere Brax imports them as it does
(:func:`unavailable` says why). ``tests/test_deferred_imports.py`` checks it on the installed versions: a PPO
run leaves both unloaded; the ``generalized`` pipeline loads JAXopt as it traces a step with constraints and steps
as with it loaded up front; eight threads loading one stand-in import it once.

Public surface: :func:`defer_brax_extras`, :func:`unavailable`, :data:`DEFERRED`, :data:`IMPORTED_ALREADY`.
"""
from __future__ import annotations

import importlib.util
import sys

from jaxrobo.core.deferred import Deferred
from jaxrobo.interop import brax_compat

#: :func:`unavailable`'s reason where this process has imported Brax's envs or checkpoint module already.
IMPORTED_ALREADY = "brax's envs or checkpoint module are imported already"

#: The modules deferred: what Brax imports at its top and calls only inside functions jaxrobo does not run.
DEFERRED = ("jaxopt", "orbax.checkpoint")


def unavailable() -> str | None:
    """Why :func:`defer_brax_extras` leaves Brax's imports as they are (a sentence), or None when it defers them:
    a Brax outside :data:`jaxrobo.interop.brax_compat.WRITTEN_FOR` (the range every Brax trick of jaxrobo was
    written for), or Brax's modules that import them imported already."""
    why = brax_compat.unavailable()
    if why is not None:
        return why
    if "brax.envs" in sys.modules or "brax.training.checkpoint" in sys.modules:
        return IMPORTED_ALREADY
    return None


def defer_brax_extras() -> list[str]:
    """Put a :class:`Deferred` stand-in in ``sys.modules`` for each of :data:`DEFERRED` that is installed and not
    imported yet (unless :func:`unavailable` says why not); the names deferred."""
    if unavailable() is not None:
        return []
    done = []
    for name in DEFERRED:
        if name in sys.modules:
            continue
        try:
            found = importlib.util.find_spec(name) is not None  # imports a parent package (orbax: a namespace)
        except (ImportError, ValueError):
            found = False
        if found:
            stand_in = sys.modules[name] = Deferred(name)
            parent, _, child = name.rpartition(".")
            if parent:  # ``import orbax.checkpoint`` then ``orbax.checkpoint.X``: the package's attribute too
                setattr(sys.modules[parent], child, stand_in)  # the real import sets it to the real module
            done.append(name)
    return done
