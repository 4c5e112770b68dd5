"""An on-screen window for Gymnasium's ``render_mode="human"``: the offscreen frames of
:class:`jaxrobo.pictures.render.Renderer`, shown with pygame (the library Gymnasium's own human rendering uses) at
the env's frame rate.

:func:`unavailable_reason` says, before a window is asked for, why none can open (pygame missing, no display, no
OpenGL to draw the frames), so ``gym.make(..., render_mode="human")`` refuses at once with that reason instead of
failing at the first ``render()``. On a machine without a screen, ``xvfb-run`` gives it a virtual one.
"""
from __future__ import annotations

import os
import sys
from typing import Any

import numpy as np

#: How to get the window's one dependency (the ``gui`` extra holds it).
INSTALL = "pip install 'jaxrobo[gui]' (or pip install pygame)"


def _pygame() -> Any:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # its import greeting would land in the user's output
    import pygame

    return pygame


def unavailable_reason() -> str | None:
    """None when a window can open in this process, else why not, on one line (the display is looked at first: a
    headless process never imports pygame)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return ("no display to open a window on (DISPLAY is unset): run under xvfb-run for a virtual screen, or use "
                "render_mode='rgb_array' for frames as arrays")
    try:
        _pygame()
    except ImportError:
        return f"a window needs pygame: {INSTALL}"
    from jaxrobo.pictures.render import gl_unavailable_reason

    return gl_unavailable_reason()


class Window:
    """One pygame window showing ``H x W x 3`` uint8 frames, paced at ``fps`` frames per second."""

    def __init__(self, title: str, fps: float):
        self.title, self.fps = title, float(fps)
        self._screen: Any = None
        self._clock: Any = None

    def show(self, frame: np.ndarray) -> None:
        pygame = _pygame()
        if self._screen is None:
            pygame.display.init()
            pygame.display.set_caption(self.title)
            self._screen = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
            self._clock = pygame.time.Clock()
        surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.swapaxes(0, 1)))
        self._screen.blit(surface, (0, 0))
        pygame.event.pump()  # a window that is not pumped is "not responding" to its desktop
        pygame.display.flip()
        self._clock.tick(self.fps)

    def close(self) -> None:
        if self._screen is not None:
            _pygame().display.quit()
            self._screen = self._clock = None
