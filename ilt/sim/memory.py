"""What a simulated scene will need in memory, computed before anything is allocated.

The simulator is dense: a scene of N patches holds several (N, N) float64 matrices at
once (form factors, transport, the pair tests of the flatland form factors, the LU
factors of the solve), so m = 40000 needs hundreds of GiB. Building one that cannot
fit would end in numpy's ``Unable to allocate`` traceback, or in swapping for hours;
:func:`require` refuses it first in one line.
"""

from __future__ import annotations

#: (N, N) float64 arrays alive at the peak of building a scene and solving its transport:
#: tracemalloc peaks of 85-112 bytes per N^2 (11-14 matrices) for N = 1024-3072, flatland
#: and box, exact and rendered; fewer than measured would let a run through that cannot finish
MATRICES_AT_PEAK = 14
#: bytes per sub-pixel ray of the box camera (ray directions, hits, the surface point and
#: patch of each ray): 150 measured by tracemalloc with few patches and many pixels
BOX_BYTES_PER_RAY = 160
#: the box camera's frame, in pixels per beam and px_per_beam^2 (1.7-1.8 measured)
BOX_PIXELS_PER_BEAM = 1.8


class InsufficientMemory(ValueError):
    """A simulation that would need more memory than the machine has available."""


def gib(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.3g} GiB"


def require(needed: int, what: str) -> None:
    """Raise :class:`InsufficientMemory` when ``needed`` bytes exceed the memory available."""
    from ilt.parallel.memory import available_memory

    available = available_memory()
    if needed > available:
        raise InsufficientMemory(f"{what} needs about {gib(needed)} of memory, {gib(available)} is available; "
                                 "use fewer beams")


def _matrices(n_patches: int) -> int:
    return MATRICES_AT_PEAK * 8 * n_patches**2


def scene_patches(name: str, beams: int) -> int:
    """Patches N of :func:`ilt.sim.scene.make_scene`'s ``name`` with ``beams``, hidden ones included."""
    if name == "occluded":
        per_facet = 2 * (beams // 8)
        return 4 * per_facet + 2 * (beams - 3 * per_facet)
    if name == "box":
        n = max(1, round((beams / 3) ** 0.5))
        return 3 * n * n
    return beams


def scene_bytes(name: str, beams: int) -> int:
    """Peak bytes of building an exact scene and its T (:func:`ilt.sim.scene.make_scene`)."""
    return _matrices(scene_patches(name, beams))


def render_bytes(name: str, beams: int, fine: int, px_per_beam: float, supersample: int) -> int:
    """Peak bytes of :func:`ilt.sim.render.render_scene` and a beam frame: the fine
    patches' (N, N) transport and its LU factors, and for the box the sub-pixel rays."""
    if name == "box":
        n = max(1, round((beams / 3) ** 0.5))
        per = max(2, fine // 4)
        rays = BOX_PIXELS_PER_BEAM * 3 * n * n * px_per_beam**2 * supersample**2
        return _matrices(3 * (n * per) ** 2) + int(BOX_BYTES_PER_RAY * rays)
    per_facet = beams // 4
    n_patches = (6 if name == "occluded" else 4) * per_facet * fine
    return _matrices(n_patches)
