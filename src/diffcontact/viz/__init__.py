"""Animations and plots of trajectories (matplotlib with the Agg canvas; no screen needed).

- :class:`Scene` (with :class:`Circle`, :class:`Chain`, :class:`Disk3D`) says what to draw;
  :func:`scene_from_system` / :func:`scene_from_config` build one for a task.
- :func:`animate` writes a GIF of one or several trajectories, optionally with an
  overlay (e.g. a prediction) drawn dashed; :func:`render_frame` saves one state as PNG.
- :func:`plot_energy` writes a PNG of energy against time.
"""

from .animation import animate, frame_indices, plot_energy, render_frame
from .scene import Chain, Circle, Disk3D, Scene, scene_from_config, scene_from_system

__all__ = [
    "Chain",
    "Circle",
    "Disk3D",
    "Scene",
    "animate",
    "frame_indices",
    "plot_energy",
    "render_frame",
    "scene_from_config",
    "scene_from_system",
]
