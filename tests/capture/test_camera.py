"""Camera backends: gphoto2 setting read-back logic, and the real libgphoto2 path
through the virtual camera inside the gphoto2 wheel (when the optional extra is installed)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ilt.capture.camera import SimCamera, match_choice, parse_setting, verify_setting
from ilt.capture.config import Exposure
from ilt.capture.errors import CameraError
from tests import ROOT


def test_setting_parsing_and_matching():
    assert parse_setting("1/8000") == parse_setting("0.000125s") and parse_setting("f/2.8") * 10 == 28
    assert parse_setting("bulb") is None
    choices = ["bulb", "30", "1/100", "1/125", "1/160", "0.0012s"]
    assert match_choice(choices, 1 / 128, "shutter speed") == "1/125"  # nominal vs true
    assert match_choice(choices, 1 / 800, "shutter speed") == "0.0012s"
    with pytest.raises(CameraError, match="no shutter speed near 0.5"):
        match_choice(choices, 0.5, "shutter speed")


def test_read_back_catches_a_setting_that_did_not_stick():
    assert verify_setting("shutterspeed", "1/125", "1/125", "Canon EOS 20D") == "1/125"
    assert verify_setting("aperture", "2.8", "f/2.8", "Canon EOS 20D") == "f/2.8"
    with pytest.raises(CameraError, match=r"shutterspeed reads back '1/60' after setting '1/125'"):
        verify_setting("shutterspeed", "1/125", "1/60", "Canon EOS 20D")


def test_sim_camera_faults_and_determinism(tmp_path):
    written = []

    def write_raw(path, radiance, t, n, rng):
        written.append(rng.integers(1 << 30))
        Path(path).write_bytes(b"x")

    cam = SimCamera(lambda: np.zeros((2, 2)), write_raw, "ilt SimSensor", seed=3, faults=["error@2", "unplug@3"])
    e = Exposure(parse_setting("1/15"), 1.2)
    cam.shoot(tmp_path / "a", e, "beam-00000/frame-00")
    with pytest.raises(CameraError, match="capture failed"):
        cam.shoot(tmp_path / "b", e, "k")
    for _ in range(2):
        with pytest.raises(CameraError, match="disconnected"):
            cam.shoot(tmp_path / "c", e, "k")
    again = SimCamera(lambda: np.zeros((2, 2)), write_raw, "ilt SimSensor", seed=3)
    again.shoot(tmp_path / "d", e, "beam-00000/frame-00")
    assert written[0] == written[1]  # same frame key, same noise: resumed runs match


VCAM_SCRIPT = r"""
import json, sys
from pathlib import Path
from fractions import Fraction
from ilt.capture.camera import GPhoto2Camera, CameraError
from ilt.capture.config import Exposure
out = {}
try:
    GPhoto2Camera(model="Canon EOS 20D", timeout=5)
except CameraError as exc:
    out["wrong_model"] = str(exc)
cam = GPhoto2Camera(model="VC", timeout=5)
path = Path(sys.argv[1]) / "shot.tmp"
out["readback"] = cam.shoot(path, Exposure(Fraction(1, 100), 2.8), "beam-00000/frame-00")
out["suffix"] = cam.suffix
out["bytes"] = path.stat().st_size
cam.close()
print(json.dumps(out))
"""


def test_gphoto2_virtual_camera(tmp_path):
    pytest.importorskip("gphoto2")
    import cv2

    vdir = tmp_path / "vcamera"
    vdir.mkdir()
    cv2.imwrite(str(vdir / "IMG_0001.jpg"), np.full((48, 64, 3), 128, np.uint8))
    env = {**os.environ, "VCAMERADIR": str(vdir), "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", VCAM_SCRIPT, str(tmp_path)], env=env,
                            capture_output=True, text=True, timeout=60)
    if result.returncode != 0 and "cannot connect" in result.stderr:
        pytest.skip(f"libgphoto2 virtual camera unavailable: {result.stderr.strip().splitlines()[-1]}")
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert "connected model is 'VC', the config wants 'Canon EOS 20D'" in out["wrong_model"]
    assert out["readback"] == {"exposure_time": "0.0100s", "f_number": "f/2.8"}
    assert out["suffix"] == ".jpg" and out["bytes"] > 0
