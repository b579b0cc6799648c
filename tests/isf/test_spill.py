"""The spill matrix: a spot's direct light in its neighbours' cells (ilt.isf.spill)."""

import numpy as np
import pytest
from scipy.special import ndtr

from ilt.isf.noise import FrameNoise
from ilt.isf.spill import Unmixing, spill_matrix, spot_spill


def noisy(frame, rng, electrons):
    """``frame`` with photon and read noise (``electrons`` at its brightest pixel, 3 e- read
    noise) and its noise model; without ``electrons``, the frame as it is and None."""
    if not electrons:
        return frame, None
    gain = electrons / frame.max()
    frame = frame + rng.normal(size=frame.shape) * np.sqrt(frame / gain + (3 / gain) ** 2)
    levels = np.linspace(0, 1200, 13)
    return frame, FrameNoise(tuple(levels), tuple(levels / gain + (3 / gain) ** 2), 1, 0, 0, 1 / gain)


def split_frame(sigma, distance, rng=None, electrons=None):
    """A Gaussian spot of ``sigma`` px ``distance`` px left of the boundary between cell 0
    (left) and cell 1, on a sloped background; with ``electrons``, photon + read noise."""
    h, w = 61, 61
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    centre = np.array([30.0 - distance, 30.0])
    spot = 1000.0 * np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * sigma**2))
    frame = spot + 2.0 + 0.01 * xx + 0.02 * yy
    labels = (xx >= 29.5).astype(np.int64)    # the boundary at x = 29.5 (pixel edges)
    frame, noise = noisy(frame, rng, electrons)
    edge = 29.5 - centre[0]
    truth = (1 - ndtr(edge / sigma)) / ndtr(edge / sigma)
    return frame, labels, centre, truth, noise


@pytest.mark.parametrize("sigma, distance", [(2.0, 2.0), (3.0, 4.0), (1.5, 1.0)])
def test_the_share_in_the_next_cell_is_the_gaussian_tail(sigma, distance):
    frame, labels, centre, truth, _ = split_frame(sigma, distance)
    share = spot_spill(frame, labels, 0, centre, 20.0)
    assert share[1] == pytest.approx(truth, rel=0.03)


def test_under_noise_the_share_holds_and_a_lone_spot_has_none():
    rng = np.random.default_rng(3)
    frame, labels, centre, truth, noise = split_frame(2.0, 2.5, rng, electrons=2e4)
    assert spot_spill(frame, labels, 0, centre, 20.0, noise)[1] == pytest.approx(truth, rel=0.1)
    far, labels, centre, _, noise = split_frame(2.0, 14.0, rng, electrons=2e4)
    assert spot_spill(far, labels, 0, centre, 20.0, noise) == {}


def test_mix_and_unmix_are_inverse_on_stacks():
    Q = spill_matrix([{1: 0.1}, {0: 0.05, 2: 0.2}, {}], 3)
    x = np.random.default_rng(0).normal(size=(3, 4, 2))
    u = Unmixing(Q)
    np.testing.assert_allclose(u.unmix(u.mix(x)), x, atol=1e-12)
    np.testing.assert_allclose(u.mix(x)[:, 0, 0], (np.eye(3) + Q.toarray()) @ x[:, 0, 0])
    out = np.empty((3, 4))
    np.testing.assert_allclose(u.unmix(x[..., 0], out=out, block=3), u.unmix(x[..., 0]), atol=1e-15)


@pytest.mark.parametrize("electrons", [None, 2e4])
def test_a_spot_on_one_row_keeps_its_flank_along_the_row(electrons):
    """A floor's spot seen at a grazing angle: sigma 1.0 px along the row, 0.5 across it,
    each pixel the Gaussian's integral over it, so only 3 pixels hold more than a quarter of
    its peak, all on one row. Cells 4 px wide (a dense scan's): the share in the next cell along
    the row is the pixel-integrated Gaussian's, within 5% (8% under photon and read noise; taken
    round from the core's area it was 0.0014 against 0.072, noise-free)."""
    h, w = 41, 41
    centre = np.array([20.0, 20.0])
    edges_x, edges_y = np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5
    along = np.diff(ndtr((edges_x - centre[0]) / 1.0))
    across = np.diff(ndtr((edges_y - centre[1]) / 0.5))
    spot = 1000.0 * across[:, None] * along[None, :] / (along.max() * across.max())
    frame = spot + 2.0
    assert ((spot > 0.25 * spot.max()).sum(), (spot > 0.25 * spot.max()).any(axis=1).sum()) == (3, 1)
    labels = np.clip((np.arange(w) + 2) // 4 - 4, 0, 2)[None, :].repeat(h, axis=0)   # cell 1: x = 18 .. 21
    own = int(labels[20, 20])
    truth = spot[labels == own + 1].sum() / spot[labels == own].sum()
    frame, noise = noisy(frame, np.random.default_rng(5), electrons)
    share = spot_spill(frame, labels, own, centre, 8.0, noise)
    assert truth > 0.02
    assert share[own + 1] == pytest.approx(truth, rel=0.08 if electrons else 0.05)
