"""The PTU driver against the emulated unit, over a real pty and a socket:// loopback."""

import time

import pytest
import serial

from ilt.capture.emulator import Fault, PTUEmulator
from ilt.capture.errors import DeviceError, Disconnected, LimitHit, PTUError, RigTimeout
from ilt.capture.ptu import PanTilt, SerialLine
from tests import ROOT

TRANSPORTS = ["pty", "socket"]


@pytest.fixture(params=TRANSPORTS)
def emu(request):
    with PTUEmulator(request.param, speed=20000) as e:
        yield e


def test_initialize_reads_resolution_and_limits(emu):
    with PanTilt(emu.port, timeout=1.0) as ptu:
        info = ptu.initialize()
        assert info["resolution_arcsec"] == {"pan": 92.5714, "tilt": 46.2857}
        assert info["limits"] == {"pan_min": -3090, "pan_max": 3090, "tilt_min": -907, "tilt_max": 604}
        # the banner arrived before the first reply and did not shift the replies
        assert emu.received[:4] == ["ED", "FT", "CI", "I"] and not emu.echo and not emu.verbose


def test_move_is_slaved_awaited_and_read_back(emu):
    with PanTilt(emu.port, timeout=1.0) as ptu:
        ptu.initialize()
        assert ptu.move(1500, -400) == (1500, -400)
        assert (emu.position("P"), emu.position("T")) == (1500, -400)
        sent = emu.received[-7:]
        assert sent == ["S", "PP1500", "TP-400", "A", "I", "PP", "TP"]


def test_out_of_limit_target_is_refused_before_moving(emu):
    with PanTilt(emu.port, timeout=1.0) as ptu:
        ptu.initialize()
        n = len(emu.received)
        with pytest.raises(PTUError, match=r"pan target 4000 outside limits \[-3090, 3090\]"):
            ptu.move(4000, 0)
        assert len(emu.received) == n  # nothing sent


def test_device_error_and_reset_reply(emu):
    with PanTilt(emu.port, timeout=1.0) as ptu:
        ptu.initialize()
        with pytest.raises(DeviceError, match="Maximum allowable Pan position is 3090"):
            ptu.line.command("PP9999")
        assert ptu.line.command("R", timeout=2.0) == ""  # '!T!T!P!P*': notices, then success
        assert ptu.line.notices == ["T", "T", "P", "P"]


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_timeout_then_recovery(transport):
    with PTUEmulator(transport, faults=["timeout:PR@1", "drop:TR@1"]) as emu, PanTilt(emu.port, timeout=0.3) as ptu:
        with pytest.raises(RigTimeout, match="no reply to 'PR' within 0.3 s"):
            ptu.initialize()
        with pytest.raises(RigTimeout, match="'TR'"):
            ptu.line.command("TR")  # executed, reply dropped
        assert float(ptu.line.command("PR")) == 92.5714  # the line works again


def test_dropped_reply_is_a_timeout():
    with PTUEmulator("pty", faults=["drop:PP@2"]) as emu, PanTilt(emu.port, timeout=0.3) as ptu:
        ptu.initialize()  # PP@1 is the read-back in initialize
        with pytest.raises(RigTimeout):
            ptu.line.command("PP")
        assert ptu.read_position() == (0, 0)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_unplug_is_disconnected(transport):
    with PTUEmulator(transport, faults=["unplug:A@1"], speed=20000) as emu, PanTilt(emu.port, timeout=0.5) as ptu:
        ptu.initialize()
        with pytest.raises((Disconnected, RigTimeout)):
            ptu.move(100, 100)
        with pytest.raises(Disconnected):
            ptu.read_position()


def test_limit_hit_during_move():
    with PTUEmulator("pty", faults=["limit:A@1"], speed=20000) as emu, PanTilt(emu.port, timeout=1.0) as ptu:
        ptu.initialize()
        with pytest.raises(LimitHit, match=r"limit hit \(!P\)"):
            ptu.move(100, 0)


def test_port_held_by_another_process_and_unknown_port():
    with PTUEmulator("pty") as emu:
        first = PanTilt(emu.port)
        try:
            with pytest.raises(PTUError, match="held by another process"):
                PanTilt(emu.port)
        finally:
            first.close()
    with pytest.raises(PTUError, match="port /dev/ilt-no-such-port does not exist"):
        PanTilt("/dev/ilt-no-such-port")


def test_parser_strips_echo_banner_and_notices():
    line = SerialLine.__new__(SerialLine)
    line.notices, line.ignored, line.what = [], [], "unit"
    assert line._parse("PP1000 * ") == ("*", "")
    assert line._parse("Initializing...") is None
    assert line._parse("!T!T!P!P*") == ("*", "")
    assert line._parse("!P") is None and line.notices == ["T", "T", "P", "P", "P"]
    assert line._parse("! Illegal Command") == ("!", "Illegal Command")
    assert line._parse("* Current Pan position is 12") == ("*", "Current Pan position is 12")


def test_fault_spec():
    assert Fault.parse("unplug:OA1@3") == Fault("unplug", "OA1", 3)
    with pytest.raises(ValueError, match="KIND:COMMAND@N"):
        Fault.parse("explode:A@1")


def test_echo_on_replies_are_parsed_raw():
    """Before ED the unit echoes; a raw pyserial session sees 'PR * 92.5714'."""
    with PTUEmulator("pty", banner="") as emu:
        with serial.Serial(emu.port, timeout=1.0) as s:
            s.write(b"PR ")
            deadline = time.monotonic() + 2
            data = b""
            while b"\n" not in data and time.monotonic() < deadline:
                data += s.read(64)
        assert data.decode().strip() == "PR * 92.5714"


def test_rig_emulator_command_serves_a_socket():
    import subprocess
    import sys

    env_path = str(ROOT)
    proc = subprocess.Popen([sys.executable, "-m", "ilt", "rig-emulator", "--socket", "0", "--speed", "20000"],
                            stdout=subprocess.PIPE, text=True, env={"PYTHONPATH": env_path, "PATH": ""})
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("socket://127.0.0.1:")
        with PanTilt(port, timeout=1.0) as ptu:
            ptu.initialize()
            assert ptu.move(-200, 100) == (-200, 100)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
