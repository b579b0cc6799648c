"""ilt.isf.layout: vectors of m samples as images (the plan's layout), and samples
splatted into and read back from camera frames."""

import numpy as np
import pytest

from ilt.isf.layout import sample_frame, splat, vector_to_image


def test_vector_to_image_is_scanline_order():
    assert np.array_equal(vector_to_image(np.arange(6), (2, 3)), [[0, 1, 2], [3, 4, 5]])
    image = vector_to_image(np.arange(12).reshape(6, 2), (3, 2))
    assert image.shape == (3, 2, 2) and np.array_equal(image[1, 0], [4, 5])
    assert vector_to_image(np.arange(5), (1, 5)).shape == (1, 5)


@pytest.mark.parametrize("layout", [(2, 4), (3, 1), (7, 1)])
def test_vector_to_image_layout_mismatch(layout):
    with pytest.raises(ValueError, match="does not hold 6 samples"):
        vector_to_image(np.arange(6), layout)
    with pytest.raises(ValueError, match="no cells"):
        vector_to_image(np.arange(6), (0, 6))


def test_vector_to_image_places_kept_beams_at_their_cells():
    image = vector_to_image(np.array([7.0, 8.0, 9.0]), (2, 3), positions=[0, 4, 5])
    assert np.array_equal(image, [[7, 0, 0], [0, 8, 9]])
    for positions in ([0, 4, 6], [1, 1, 2], [0.0, 1.0, 2.0], [0, 1]):
        with pytest.raises(ValueError, match="3 distinct cells of the 2 x 3 layout"):
            vector_to_image(np.ones(3), (2, 3), positions=positions)


def _samples(m, frame_shape, seed=0):
    """m sample points on distinct pixels of the frame, with subpixel jitter below 0.5."""
    rng = np.random.default_rng(seed)
    height, width = frame_shape
    pixels = rng.choice(height * width, size=m, replace=False)
    jitter = rng.uniform(-0.49, 0.49, size=(m, 2))
    return np.column_stack([pixels % width, pixels // width]) + jitter


@pytest.mark.parametrize("k", [None, 3])
def test_sample_frame_inverts_splat(k):
    rng = np.random.default_rng(1)
    values = rng.standard_normal((40,) if k is None else (40, k)).astype(np.float32)
    samples = _samples(40, (11, 13))
    image = splat(values, samples, (11, 13), fill=-1.0)
    assert image.dtype == np.float32 and image.shape == (11, 13, *values.shape[1:])
    assert np.array_equal(sample_frame(image, samples), values)
    assert sample_frame(image, samples).dtype == np.float64
    assert np.count_nonzero(image == -1.0) == (11 * 13 - 40) * (k or 1)


def test_splat_rounds_to_the_nearest_pixel_centre():
    image = splat([1.0, 2.0, 3.0], [[0.0, 0.0], [1.49, 0.51], [2.5, 1.5]], (3, 4))
    # halves round up: (2.5, 1.5) is pixel row 2, column 3
    assert np.array_equal(image, [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 0, 3]])


@pytest.mark.parametrize("point", [(-0.6, 0.0), (0.0, 2.5), (3.5, 1.0), (np.nan, 0.0)])
def test_out_of_frame_samples_are_named(point):
    samples = [[0.0, 0.0], [1.0, 1.0], point]
    with pytest.raises(ValueError, match="sample 2 "):
        splat([1.0, 2.0, 3.0], samples, (3, 4))
    with pytest.raises(ValueError, match="sample 2 "):
        sample_frame(np.zeros((3, 4)), samples)


def test_splat_refuses_two_samples_on_one_pixel():
    with pytest.raises(ValueError, match="samples 0 and 2 fall on the same pixel"):
        splat([1.0, 2.0, 3.0], [[1.2, 1.0], [0.0, 0.0], [0.8, 1.3]], (3, 4))
