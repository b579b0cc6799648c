"""ilt.io.preview: log scaling and the PNG figures."""

import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest

from ilt.io.preview import (
    IMAGE_SIZE,
    PANEL_SIZE,
    _bounce_canvas,
    bounce_panel,
    gain_title,
    log_scale,
    matrix_panel,
    nice_gain,
    save_png,
)

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


def _png(path):
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return cv2.imread(str(path))


def _png_size(path):
    height, width = _png(path).shape[:2]
    return width, height


def _panel_size(n):
    return PANEL_SIZE[0] * n, PANEL_SIZE[1]


def _isf(m=30):
    """A near-diagonal transport matrix like the paper's Fig. 5 T."""
    i, j = np.indices((m, m))
    return np.exp(-np.abs(i - j)) + 1e-4 * np.exp(-((i - j - m / 3) ** 2) / 20)


def _bright_magma(picture):
    """Pixels near the top of the magma map (pale yellow: not white, not dark)."""
    b, g, r = np.moveaxis(picture.astype(int), 2, 0)
    return (g > 200) & (r > 200) & (b < g - 30)


def test_save_png_writes_an_image_of_the_figure_size(tmp_path):
    path = save_png(tmp_path / "t.png", _isf(), title="T")
    assert _png_size(path) == (640, 480) == IMAGE_SIZE
    assert _png_size(save_png(tmp_path / "strip.png", np.arange(50.0)[None], log=False)) == (640, 480)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strip.png", "t.png"]


def test_matrix_panel_like_fig5(tmp_path):
    t = _isf()
    c1t = np.eye(30)
    matrices = {"T": t, "C1 T": c1t, "C2 T": 0.1 * t @ t, "T - C1 T": t - c1t, "zero": np.zeros((30, 30))}
    path = matrix_panel(tmp_path / "fig5.png", matrices)
    assert _png_size(path) == _panel_size(5) == (1600, 360)
    picture = _png(path)
    cell = (1600 - 80) // 5  # each panel's share of the width left of the colour bar
    bright = [_bright_magma(picture[:, k * cell:(k + 1) * cell]).sum() for k in range(5)]
    # the diagonal of C1 T: 30 of 900 elements at its max; T is bright on a band; zero is all floor
    assert bright[1] > 1000 and bright[0] > bright[1] and bright[4] == 0, bright
    assert _png_size(matrix_panel(tmp_path / "lin.png", {"T": t}, log=False)) == _panel_size(1)


def test_matrix_panel_pools_large_matrices(tmp_path):
    big = np.eye(3000)[:, :2500]
    picture = _png(matrix_panel(tmp_path / "big.png", {"T": big}))
    assert picture.shape[1::-1] == _panel_size(1)
    # max pooling keeps the diagonal: in every row of the panel where the matrix has it
    rows = np.flatnonzero(_bright_magma(picture[:, :240]).any(axis=1))
    assert len(rows) > 0.8 * 274 * 2500 / 3000, len(rows)


def test_nice_gain_is_the_largest_round_factor_not_past_the_photo():
    assert nice_gain(100, 3) == 20  # 1.1 * 100 / 3 = 36.7
    assert nice_gain(100, 21) == 5  # 5.24: 10 % over the photo is allowed
    assert nice_gain(100, 30) == 2  # 3.67
    assert nice_gain(1, 0.1) == 10 and nice_gain(1, 1e-3) == 1000 and nice_gain(7, 7e-6) == 1e6
    assert nice_gain(1, 0.6) == 1 and nice_gain(1, 1) == 1 and nice_gain(1, 5) == 1  # never dimmer
    assert nice_gain(0, 1) == nice_gain(1, 0) == nice_gain(1, -2) == nice_gain(1, 5e-324) == 1
    assert gain_title("bounce 2", 20.0) == "bounce 2 ×20" and gain_title("photo", 1.0) == "photo"
    assert gain_title("L8", 1e6) == "L8 ×1000000"


def _regions(images, **kw):
    canvas, boxes = _bounce_canvas(images, kw.get("log", False), kw.get("floor_decades", 6.0))
    return canvas, [canvas[y:y + h, x:x + w, 0].astype(int) for x, y, w, h in boxes], boxes


def test_bounce_panel_like_fig6(tmp_path):
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.5, 1.0, (24, 32))
    images = {"photo": photo, "1 bounce": 0.7 * photo, "2 bounces": photo / 12, "dark": np.zeros((24, 32))}
    width, height = _png_size(bounce_panel(tmp_path / "fig6.png", images))
    assert 4 * 320 < width < 4 * 320 + 250 and height < 360
    _, regions, boxes = _regions(images)
    assert [b[2:] for b in boxes] == [(320, 240)] * 4  # 320 on the long side
    assert regions[0].min() > 100 and regions[2].min() > 100  # not blank where the image is not
    assert regions[3].max() == 0
    # one grey scale: 1 bounce is not stretched to white, 2 bounces shown at x10 of 1/12
    assert np.abs(regions[1] - 0.7 * regions[0]).max() <= 1.5
    assert np.abs(regions[2] - regions[0] * 10 / 12).max() <= 1.5
    strips = {"photo": photo[:1], "3 bounces": photo[:1] / 4}
    _, _, boxes = _regions(strips, log=True)
    assert [b[2:] for b in boxes] == [(960, 120)] * 2  # 1 x 32 stretched to 1:8, one a row
    width, height = _png_size(bounce_panel(tmp_path / "strip.png", strips, log=True))
    assert width < 1200 and height < 2 * 170


def test_identical_images_get_identical_grey_levels():
    rng = np.random.default_rng(1)
    photo = rng.uniform(0, 1, (30, 40))
    _, regions, _ = _regions({"photo": photo, "same": photo.copy(), "a": photo / 12, "b": photo / 12})
    assert np.array_equal(regions[0], regions[1]) and np.array_equal(regions[2], regions[3])
    assert regions[0].std() > 20


def test_bounce_panel_log_is_decades_below_the_photo():
    photo = np.full((8, 8), 5.0)
    _, regions, _ = _regions({"photo": photo, "tenth": photo / 10, "tiny": photo * 1e-9}, log=True,
                             floor_decades=2.0)
    assert regions[0].min() == 255 and np.all(np.abs(regions[1] - 128) <= 1) and regions[2].max() == 0


@pytest.mark.parametrize("shape", [(32, 1553), (300, 400), (2000, 3000), (18, 6), (1, 12)])
def test_full_resolution_frames_fit_in_2000_pixels(tmp_path, shape):
    y, x = np.indices(shape) / np.array(shape)[:, None, None]
    photo = (np.sin(12 * x) * np.cos(5 * y) + 1).astype(np.float32)
    images = {"photo": photo, **{f"bounce {n}": photo * 0.3 ** n for n in range(1, 9)}, "indirect": photo * 0.4}
    width, height = _png_size(bounce_panel(tmp_path / "f.png", images))
    assert width <= 2000 and height <= 2000
    _, regions, boxes = _regions(images)
    long_sides = {max(w, h) for _, _, w, h in boxes}
    assert long_sides <= {320, 960} if shape[1] < 3 * shape[0] else long_sides == {960}
    assert all(r.std() > 10 for r in regions), [r.std() for r in regions]


def test_negative_and_non_finite_values_show_black():
    photo = np.ones((10, 10))
    photo[0, 0], photo[1, 1], photo[2, 2] = np.nan, np.inf, -np.inf
    noisy = -np.ones((10, 10))
    _, regions, _ = _regions({"photo": photo, "negative": noisy, "nan": np.full((10, 10), np.nan)})
    assert regions[0].max() == 255 and regions[0].min() == 0
    assert regions[1].max() == 0 and regions[2].max() == 0


def test_preview_does_not_import_matplotlib():
    code = "import sys, ilt.io.preview; print(sorted(m for m in sys.modules if m.startswith('matplotlib')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_png_writes_are_atomic(tmp_path):
    with pytest.raises(ValueError, match="missing"):
        save_png(tmp_path / "missing" / "a.png", _isf(4))
    with pytest.raises(ValueError, match="2D"):
        matrix_panel(tmp_path / "a.png", {"T": np.ones(3)})
    with pytest.raises(ValueError, match="2D"):
        bounce_panel(tmp_path / "a.png", {"photo": np.ones((3, 3)), "bad": np.ones(3)})
    with pytest.raises(ValueError, match="end in .png"):
        bounce_panel(tmp_path / "a.jpg", {"photo": np.ones((3, 3))})
    assert list(tmp_path.iterdir()) == []
