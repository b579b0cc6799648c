"""The simulated sensor: DNG files rawpy reads back exactly, and its expected values."""

import numpy as np
import pytest
import rawpy

from ilt.sim.sensor import SensorModel, expected_dn, expose, write_dng


def test_dng_round_trip_through_rawpy(tmp_path):
    sensor = SensorModel(width=48, height=32, cfa="GBRG", black_level=512, white_level=4000, bits=12)
    mosaic = np.random.default_rng(0).integers(0, 4000, (32, 48)).astype(np.uint16)
    path = write_dng(tmp_path / "x.dng", np.zeros((32, 48)), 1 / 250, 2.8, sensor,
                     np.random.default_rng(0), mosaic=mosaic)
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic)
        desc = raw.color_desc.decode()
        assert "".join(desc[c] for c in raw.raw_colors_visible[:2, :2].ravel()) == "GBRG"
        assert list(raw.black_level_per_channel) == [512] * 4 and raw.white_level == 4000
        assert raw.other.aperture == pytest.approx(2.8)


def test_mean_of_exposures_is_the_expected_dn():
    sensor = SensorModel(width=32, height=24, read_noise=3.0)
    X = np.full((24, 32), 5e5)
    rng = np.random.default_rng(1)
    mean = np.mean([expose(X, 1 / 100, 2.0, sensor, rng) for _ in range(200)], axis=0)
    truth = expected_dn(X, 1 / 100, 2.0, sensor)
    # linear below clipping: black + radiance * colour scale * t / N^2 / gain
    np.testing.assert_allclose(truth - 1024, X * np.array(sensor.colour_scale)[sensor.colour_index()] / 400)
    sd = np.sqrt((truth - 1024) / sensor.gain + 9) / np.sqrt(200)
    assert np.all(np.abs(mean - truth) < 5 * sd + 0.05)


def test_bad_sensor_is_refused():
    with pytest.raises(ValueError, match="Bayer"):
        SensorModel(cfa="RGBG")
