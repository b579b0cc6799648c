"""Synthetic Lambertian scenes with exactly known transport (DESIGN.md sec. 5).

``make_scene(name)`` builds the flatland M (paper Fig. 3), a textured M, an M
under an occluder, or three inside faces of a box (Fig. 7), with the true ``A``,
``T1``, ``T``, n-bounce ISFs and photos under flashlight, room and projector light.
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "lighting": ["ILLUMINATIONS"],
        "scene": ["SCENES", "Scene", "make_scene"],
        "render": ["render_scene"],
        "sensor": ["SensorModel", "write_bracket", "write_dng"],
    },
)
