"""Synthetic Lambertian scenes with exactly known transport (DESIGN.md sec. 5).

``make_scene(name)`` builds the flatland M (paper Fig. 3), a textured M, an M
under an occluder, or three inside faces of a box (Fig. 7), with the true ``A``,
``T1``, ``T``, n-bounce ISFs and photos under flashlight, room and projector light.
"""

from .lighting import ILLUMINATIONS
from .scene import SCENES, Scene, make_scene

__all__ = ["ILLUMINATIONS", "SCENES", "Scene", "make_scene"]
