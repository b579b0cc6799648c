"""Driver for FLIR/Directed Perception pan-tilt units (PTU-D46/D48/E46) over pyserial.

The ASCII protocol: a command ends with a space (or CR); the unit answers ``*``,
``* value`` or ``! message``, may echo what it receives (on at power-up), and sends
``!P`` / ``!T`` unprompted whenever an axis hits a limit. :class:`SerialLine` is that
request/reply convention (also used by a laser on its own line); :class:`PanTilt`
initialises the unit (echo off ``ED``, terse ``FT``, independent control ``CI``), reads
its resolution (``PR``/``TR``, arc-seconds per step) and limits (``PN/PX/TN/TX``), and
moves both axes together (slaved mode ``S``, ``PP``/``TP``, await ``A``) after checking
the target against the limits, then reads the position back.
"""

from __future__ import annotations

import errno
import logging
import re
import time

import serial

from .errors import DeviceError, Disconnected, LimitHit, PTUError, RigTimeout

log = logging.getLogger(__name__)

_NOTICE = re.compile(r"!([PTD])(?=$|[!*\s])")


def open_serial(port: str, baud: int, what: str) -> serial.SerialBase:
    """Open a device path or pyserial URL exclusively; errors name the port and the cause."""
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=0.02, write_timeout=2.0, exclusive=True)
    except serial.SerialException as exc:
        text = str(exc)
        code = exc.errno if isinstance(exc.errno, int) else None
        if code in (errno.EAGAIN, errno.EWOULDBLOCK) or "exclusively lock" in text:
            raise PTUError(f"{what}: port {port} is held by another process (close it, or check `fuser {port}`)") from None
        if code == errno.ENOENT or "No such file" in text:
            raise PTUError(f"{what}: port {port} does not exist (unplugged? check the [ptu]/[laser] port)") from None
        if code == errno.EACCES or "Permission denied" in text:
            raise PTUError(f"{what}: no permission to open port {port} (add yourself to the dialout group)") from None
        raise PTUError(f"{what}: cannot open port {port}: {text}") from None
    except (ValueError, OSError) as exc:
        raise PTUError(f"{what}: cannot open port {port}: {exc}") from None


class SerialLine:
    """One request, one reply, on a line that speaks ``*`` / ``! message``.

    ``notices`` collects the unprompted ``!P``/``!T``/``!D`` seen so far (axis letters).
    """

    def __init__(self, port: str, baud: int = 9600, timeout: float = 2.0, what: str = "pan-tilt unit"):
        self.port, self.what, self.timeout = port, what, timeout
        self.notices: list[str] = []
        self.ignored: list[str] = []  # banner and echo text, for the record
        self._buf = ""
        self._ser = open_serial(port, baud, what)

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except (serial.SerialException, OSError):
                pass
            self._ser = None

    @property
    def closed(self) -> bool:
        return self._ser is None

    def _receive(self) -> str:
        try:
            data = self._ser.read(max(1, self._ser.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise Disconnected(f"{self.what} on {self.port} disconnected ({exc})") from None
        return data.decode("ascii", "replace")

    def _waiting(self) -> int:
        """How many bytes the device has sent that are not read yet; Disconnected when the
        line is gone."""
        try:
            return self._ser.in_waiting
        except (serial.SerialException, OSError) as exc:
            raise Disconnected(f"{self.what} on {self.port} disconnected ({exc})") from None

    def drain(self, quiet: float = 0.0) -> list[str]:
        """Read what the device sent unasked (banner, late replies, limit notices) until
        it has been quiet for ``quiet`` seconds; return its lines."""
        lines = []
        last = time.monotonic()
        while True:
            if not quiet and not self._waiting():
                break                      # nothing sent unasked: no read to wait out its timeout
            chunk = self._receive()
            if chunk:
                self._buf += chunk
                last = time.monotonic()
            elif time.monotonic() - last >= quiet:
                break
        *complete, self._buf = self._buf.split("\n")
        if self._buf and quiet:
            complete.append(self._buf)
            self._buf = ""
        for line in complete:
            if line.strip():
                self._parse(line)
                lines.append(line.strip())
        return lines

    def _parse(self, line: str) -> tuple[str, str] | None:
        """('*', value) or ('!', message) from one line, None for noise; notices collected.

        Anything before the first ``*`` or ``!`` is echo or banner text.
        """
        start = min((i for i in (line.find("*"), line.find("!")) if i >= 0), default=-1)
        if start < 0:
            if line.strip():
                self.ignored.append(line.strip())
                log.debug("%s: ignored %r", self.what, line.strip())
            return None
        rest = line[start:].strip()
        while m := _NOTICE.match(rest):
            self.notices.append(m.group(1))
            log.info("%s: unprompted !%s (%s)", self.what, m.group(1),
                     {"P": "pan limit hit", "T": "tilt limit hit", "D": "cable disconnect"}[m.group(1)])
            rest = rest[m.end():].lstrip()
        if not rest:
            return None
        return rest[0], rest[1:].strip()

    def command(self, text: str, timeout: float | None = None) -> str:
        """Send ``text`` and return the reply's value ('' for a plain ``*``).

        Raises RigTimeout, DeviceError (with the unit's message) or Disconnected.
        """
        if self._ser is None:
            raise Disconnected(f"{self.what} on {self.port} is closed")
        self.drain()
        try:
            self._ser.write((text + " ").encode("ascii"))
            self._ser.flush()
        except (serial.SerialException, OSError) as exc:
            raise Disconnected(f"{self.what} on {self.port} disconnected ({exc})") from None
        limit = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline:
            chunk = self._receive()
            if not chunk:
                continue
            self._buf += chunk
            while "\n" in self._buf:
                line, self._buf = self._buf.split("\n", 1)
                reply = self._parse(line)
                if reply is None:
                    continue
                kind, value = reply
                if kind == "!":
                    raise DeviceError(f"{self.what} on {self.port}: command {text!r} failed: {value}")
                return value
        raise RigTimeout(f"{self.what} on {self.port}: no reply to {text!r} within {limit:.1f} s")


def _number(value: str, what: str) -> float:
    m = re.search(r"-?\d+(?:\.\d+)?", value)
    if not m:
        raise PTUError(f"pan-tilt unit: expected a number for {what}, got {value!r}")
    return float(m.group())


class PanTilt:
    """A pan-tilt unit: ``info`` holds what :meth:`initialize` read (for the manifest)."""

    def __init__(self, port: str, baud: int = 9600, timeout: float = 2.0, speed: int | None = None):
        self.line = SerialLine(port, baud, timeout, "pan-tilt unit")
        self.timeout = timeout
        self.speed_setting = speed
        self.info: dict = {}
        self.position: tuple[int, int] | None = None

    def close(self) -> None:
        self.line.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def initialize(self) -> dict:
        """Echo off, terse feedback, independent control; read resolution, limits, speeds."""
        self.line.drain(quiet=0.2)
        for cmd in ("ED", "FT", "CI", "I"):
            self.line.command(cmd)
        if self.speed_setting:
            self.line.command(f"PS{int(self.speed_setting)}")
            self.line.command(f"TS{int(self.speed_setting)}")
        q = {c: _number(self.line.command(c), c) for c in ("PR", "TR", "PN", "PX", "TN", "TX", "PS", "TS")}
        self.info = {
            "port": self.line.port,
            "banner": list(self.line.ignored),
            "resolution_arcsec": {"pan": q["PR"], "tilt": q["TR"]},
            "limits": {"pan_min": int(q["PN"]), "pan_max": int(q["PX"]),
                       "tilt_min": int(q["TN"]), "tilt_max": int(q["TX"])},
            "speed": {"pan": q["PS"], "tilt": q["TS"]},
        }
        self.line.notices.clear()
        self.position = self.read_position()
        return self.info

    @property
    def resolution(self) -> tuple[float, float]:
        r = self.info["resolution_arcsec"]
        return r["pan"], r["tilt"]

    def read_position(self) -> tuple[int, int]:
        return int(_number(self.line.command("PP"), "PP")), int(_number(self.line.command("TP"), "TP"))

    def check(self, pan: int, tilt: int) -> None:
        lim = self.info["limits"]
        for axis, v in (("pan", pan), ("tilt", tilt)):
            if not lim[f"{axis}_min"] <= v <= lim[f"{axis}_max"]:
                raise PTUError(f"pan-tilt unit: {axis} target {v} outside limits "
                               f"[{lim[f'{axis}_min']}, {lim[f'{axis}_max']}]")

    def move(self, pan: int, tilt: int) -> tuple[int, int]:
        """Move both axes together and return the position read back (steps).

        Raises PTUError before moving when the target is outside the limits; LimitHit
        when the unit reports ``!P``/``!T`` during the move; PTUError when the
        read-back position is not the target.
        """
        pan, tilt = int(pan), int(tilt)
        self.check(pan, tilt)
        start = self.position or self.read_position()
        travel = max(abs(pan - start[0]) / self.info["speed"]["pan"], abs(tilt - start[1]) / self.info["speed"]["tilt"])
        self.line.notices.clear()
        self.position = None  # unknown until read back
        self.line.command("S")
        self.line.command(f"PP{pan}")
        self.line.command(f"TP{tilt}")
        self.line.command("A", timeout=self.timeout + 1.5 * travel)
        self.line.command("I")
        if self.line.notices:
            hit = ", ".join(sorted(set(self.line.notices)))
            raise LimitHit(f"pan-tilt unit: limit hit (!{hit}) moving to pan {pan}, tilt {tilt}")
        got = self.read_position()
        if got != (pan, tilt):
            raise PTUError(f"pan-tilt unit: moved to pan {got[0]}, tilt {got[1]} instead of {pan}, {tilt}")
        self.position = got
        return got
