"""ilt.sim.render: rendered camera frames against the exact transport they come from."""

import numpy as np
import pytest

from ilt.sim.render import render_scene


@pytest.fixture(scope="module")
def flat():
    return render_scene("m", beams=16, fine=8)


@pytest.fixture(scope="module")
def box():
    return render_scene("box", beams=12, fine=8, px_per_beam=24)


def test_surface_is_finer_than_the_beam_grid(flat, box):
    assert len(flat.geometry.area) == 8 * flat.m
    assert len(box.geometry.area) == 4 * box.m          # 2 x 2 fine patches per beam
    assert flat.frame_shape[0] >= 32 and flat.extruded and not box.extruded


@pytest.mark.parametrize("name", ["flat", "box"])
def test_a_beam_delivers_unit_power(name, request):
    scene = request.getfixturevalue(name)
    g = scene.geometry
    for j in (0, scene.m // 2, scene.m - 1):
        direct = scene.beam_direct(j)
        np.testing.assert_allclose((direct * g.area / g.albedo).sum(), 1.0, rtol=1e-12)
        assert (direct > 0).sum() > 1                  # a footprint, not one patch


def test_spot_is_a_blob_centred_on_the_beam(flat):
    # flatland: the imaged spot's first moment is the beam axis's pixel column
    x0 = flat.centres[:, 0] - flat.targets[:, 0] * (flat.centres[1, 0] - flat.centres[0, 0]) / (
        flat.targets[1, 0] - flat.targets[0, 0])
    np.testing.assert_allclose(x0, x0[0], atol=1e-9)
    image = flat.spot_image(3)
    assert image.max() > 0 and (image > 0.5 * image.max()).sum() >= 4


def test_box_centres_are_close_to_the_projected_axis(box):
    from ilt.sim.geometry import BOX_EYE
    from ilt.sim.render import _box_camera, _project

    forward, right, up = _box_camera()
    uv = _project(box.targets, forward, right, up)
    # same affine map as the camera: fit it and compare
    design = np.c_[uv, np.ones(len(uv))]
    coef, *_ = np.linalg.lstsq(design, box.centres, rcond=None)
    assert np.abs(design @ coef - box.centres).max() < 0.03
    assert np.isfinite(BOX_EYE).all()


def test_photo_bounces_sum_to_the_photo(flat):
    photo, bounces = flat.photo("room", n_bounces=40)
    np.testing.assert_allclose(bounces.sum(axis=0), photo, rtol=1e-4, atol=1e-6)
    assert (photo[:, :8] == 0).all()                   # margin pixels see nothing


def test_beam_frame_is_spot_plus_exact_interreflections(flat):
    j = 5
    frame = flat.beam_frame(j)
    direct = flat.beam_direct(j)
    scattered = flat.to_frame(flat.radiosity(direct) - direct)
    np.testing.assert_allclose(frame, flat.spot_image(j) + scattered, rtol=1e-5, atol=1e-6)
    # the spot's own cell holds far more than the interreflected light elsewhere
    assert frame.max() > 100 * np.median(frame[frame > 0])


def test_unknown_scene_and_bad_spot():
    with pytest.raises(ValueError, match="unknown scene"):
        render_scene("teapot")
    with pytest.raises(ValueError, match="spot"):
        render_scene("m", spot=0)


def test_a_beam_between_plan_beams_lands_between_them(flat, box):
    """beam_between: at a plan position it is that beam; halfway inside a face, the
    spot is halfway (flatland: exactly, the orthographic column) with unit power; across
    the M's fold it lands on the surface the column between them sees."""
    np.testing.assert_allclose(flat.beam_between((5,)).beam_frame(0), flat.beam_frame(5), rtol=0, atol=1e-6)
    np.testing.assert_allclose(box.beam_between((1, 0)).beam_frame(0), box.beam_frame(1), rtol=0, atol=1e-6)
    assert flat.target_facet[5] == flat.target_facet[6]
    half = flat.beam_between((5.5,))
    np.testing.assert_allclose(half.centres[0], flat.centres[5:7].mean(axis=0), atol=1e-6)
    g = half.geometry
    np.testing.assert_allclose((half.beam_direct(0) * g.area / g.albedo).sum(), 1.0, rtol=1e-12)
    quarter = box.beam_between((0.25, 0.0))
    np.testing.assert_allclose(quarter.targets[0], 0.75 * box.targets[0] + 0.25 * box.targets[1], atol=1e-12)
    fold = int(np.flatnonzero(np.diff(flat.target_facet))[0])
    across = flat.beam_between((fold + 0.5,))
    x = flat.targets[fold:fold + 2, 0].mean()
    assert across.targets[0, 0] == pytest.approx(x)
    from ilt.sim.render import _flatland_topmost

    patch, point = _flatland_topmost(flat.geometry, np.array([[x]]))
    assert across.targets[0, 1] == pytest.approx(point[0, 0, 1])
    assert across.target_facet[0] == flat.geometry.facet[patch[0, 0]]
