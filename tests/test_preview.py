"""ilt.layout and ilt.preview: vectors as images, log scaling and the PNG figures."""

import warnings

import matplotlib
import matplotlib.image
import numpy as np
import pytest

from ilt.layout import sample_frame, splat, vector_to_image
from ilt.preview import (
    DPI,
    IMAGE_INCHES,
    PANEL_INCHES,
    bounce_panel,
    log_scale,
    matrix_panel,
    save_png,
)

# ---------------------------------------------------------------- layout


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


# ---------------------------------------------------------------- log_scale


def test_log_scale_known_values():
    x = np.array([2.0, 2e-3, 2e-6, 2e-9, 0.0, -5.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        y = log_scale(x, floor_decades=6.0)
        assert np.array_equal(log_scale(np.zeros((3, 3))), np.zeros((3, 3)))
        assert np.array_equal(log_scale(-np.ones(4)), np.zeros(4))
        assert log_scale(np.array([1e300, 5e-324]))[1] == 0.0
    assert np.allclose(y, [1.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    assert log_scale(np.array([1.0, 0.1]), floor_decades=2.0)[1] == pytest.approx(0.5)


def test_log_scale_refuses_nan():
    with pytest.raises(ValueError, match="non-finite"):
        log_scale(np.array([1.0, np.nan]))


# ---------------------------------------------------------------- PNG figures


def _png_size(path):
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    height, width = matplotlib.image.imread(path).shape[:2]
    return width, height


def _panel_size(n):
    return round(PANEL_INCHES[0] * n * DPI), round(PANEL_INCHES[1] * DPI)


def _isf(m=30):
    """A near-diagonal transport matrix like the paper's Fig. 5 T."""
    i, j = np.indices((m, m))
    return np.exp(-np.abs(i - j)) + 1e-4 * np.exp(-((i - j - m / 3) ** 2) / 20)


def test_save_png_writes_an_image_of_the_figure_size(tmp_path):
    path = save_png(tmp_path / "t.png", _isf(), title="T")
    assert _png_size(path) == (640, 480) == (IMAGE_INCHES[0] * DPI, IMAGE_INCHES[1] * DPI)
    assert _png_size(save_png(tmp_path / "strip.png", np.arange(50.0)[None], log=False)) == (640, 480)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strip.png", "t.png"]


def test_matrix_panel_like_fig5(tmp_path):
    t = _isf()
    c1t = np.eye(30)
    matrices = {"T": t, "C1 T": c1t, "C2 T": 0.1 * t @ t, "T - C1 T": t - c1t, "zero": np.zeros((30, 30))}
    path = matrix_panel(tmp_path / "fig5.png", matrices)
    assert _png_size(path) == _panel_size(5)
    assert _png_size(matrix_panel(tmp_path / "lin.png", {"T": t}, log=False)) == _panel_size(1)


def test_matrix_panel_pools_large_matrices(tmp_path):
    big = np.eye(3000)[:, :2500]
    assert _png_size(matrix_panel(tmp_path / "big.png", {"T": big})) == _panel_size(1)


def test_bounce_panel_like_fig6(tmp_path):
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.5, 1.0, (24, 32))
    images = {"photo": photo, "1 bounce": 0.7 * photo, "2 bounces": photo / 12, "dark": np.zeros((24, 32))}
    path = bounce_panel(tmp_path / "fig6.png", images)
    assert _png_size(path) == _panel_size(4)
    strips = {"photo": photo[:1], "3 bounces": photo[:1] / 4}
    assert _png_size(bounce_panel(tmp_path / "strip.png", strips, log=True)) == _panel_size(2)


def test_bounce_panel_titles_give_the_scale_factor(tmp_path, monkeypatch):
    titles = []
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title", lambda ax, t, *a, **k: titles.append(t))
    photo = np.full((4, 4), 12.0)
    bounce_panel(tmp_path / "f.png", {"photo": photo, "2 bounces": photo / 4, "3 bounces": photo / 12})
    assert titles == ["photo", "2 bounces ×4", "3 bounces ×12"]


def test_no_figures_are_left_open(tmp_path):
    import matplotlib.pyplot as plt

    before = plt.get_fignums()
    for k in range(2):
        save_png(tmp_path / f"a{k}.png", _isf(8))
        matrix_panel(tmp_path / f"b{k}.png", {"T": _isf(8)})
        bounce_panel(tmp_path / f"c{k}.png", {"photo": _isf(8)})
    assert plt.get_fignums() == before


def test_png_writes_are_atomic(tmp_path):
    with pytest.raises(ValueError, match="missing"):
        save_png(tmp_path / "missing" / "a.png", _isf(4))
    with pytest.raises(ValueError, match="2D"):
        matrix_panel(tmp_path / "a.png", {"T": np.ones(3)})
    assert list(tmp_path.iterdir()) == []
