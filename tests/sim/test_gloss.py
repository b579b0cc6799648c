"""The glossy flatland simulator: Lambertian at gloss 0, closure, the lobe's normalisation, the verdict."""

import numpy as np
import pytest

from ilt.sim.gloss import _QUADRATURE, glossy_scene
from ilt.sim.scene import make_scene
from ilt.transport.reciprocity import reciprocity_check


@pytest.fixture(scope="module")
def scenes():
    return {name: make_scene(name, 32) for name in ("m", "occluded")}


def test_no_gloss_is_the_lambertian_scene_exactly(scenes):
    for scene in scenes.values():
        glossy = glossy_scene(scene, 0.0)
        T, scale = glossy.isf()
        T0, scale0 = scene.isf()
        np.testing.assert_allclose(T, T0, atol=1e-13)
        np.testing.assert_allclose(scale, scale0, rtol=1e-12)
        for kind in ("flashlight", "room", "projector"):
            np.testing.assert_allclose(glossy.photo(kind, 2)[0], scene.photo(kind, 2)[0], rtol=1e-12, atol=1e-15)


def test_a_glossy_photo_is_the_sum_of_its_bounces(scenes):
    glossy = glossy_scene(scenes["m"], 0.6)
    photo, bounces = glossy.photo("flashlight", 60)
    np.testing.assert_allclose(bounces.sum(axis=0), photo, rtol=1e-10, atol=1e-14 * photo.max())
    assert (bounces >= 0).all()


def test_the_lobe_reflects_what_a_matte_patch_does():
    """integral of l cos over the half-plane is 2 (a matte patch's l = 1), wherever the mirror direction lies."""
    glossy = glossy_scene(make_scene("m", 8), 1.0, lobe_deg=10.0)
    normal = glossy.scene.geometry.normal[0]
    tangent = np.array([normal[1], -normal[0]])
    for angle in np.radians([0.0, 30.0, 70.0]):
        mirror = np.cos(angle) * normal + np.sin(angle) * tangent
        incoming = mirror - 2 * (mirror @ normal) * normal
        outgoing = np.cos(_QUADRATURE)[:, None] * normal + np.sin(_QUADRATURE)[:, None] * tangent
        lobe = glossy._lobe(np.zeros(len(_QUADRATURE), dtype=int), np.broadcast_to(incoming, outgoing.shape), outgoing)
        assert np.trapezoid(lobe * np.cos(_QUADRATURE), _QUADRATURE) == pytest.approx(2.0, rel=1e-6)


@pytest.mark.parametrize("gloss, noise, verdict", [
    (0.0, 0.0, "lambertian"), (0.05, 0.0, "lambertian"), (0.2, 0.0, "not lambertian"), (0.5, 0.0, "not lambertian"),
    (0.0, 0.02, "lambertian"), (0.5, 0.02, "not lambertian"), (0.5, 0.3, "undecided"),
])
def test_the_verdict_flips_as_gloss_grows_until_noise_hides_it(scenes, gloss, noise, verdict):
    """The M's T with a glossy share, and photon-like noise of relative sigma ``noise`` on every entry:
    at 0.3 no pair stands 10 sigmas above its noise, and the check says it cannot tell."""
    T, _ = glossy_scene(scenes["m"], gloss).isf()
    var = None
    if noise:
        var = (noise * T) ** 2 + (1e-4 * T.max()) ** 2
        T = T + np.random.default_rng(5).normal(0, 1, T.shape) * np.sqrt(var)
    r = reciprocity_check(T, var)
    assert r.verdict == verdict, r.reason


def test_glossy_scenes_are_flatland_only():
    with pytest.raises(ValueError, match="flatland only"):
        glossy_scene(make_scene("box", 12), 0.3)
    with pytest.raises(ValueError, match=r"gloss must be in \[0, 1\]"):
        glossy_scene(make_scene("m", 8), 1.5)
