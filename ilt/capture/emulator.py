"""An emulated FLIR/Directed Perception pan-tilt unit (PTU-D46/D48/E46 ASCII protocol).

It speaks the protocol on a pseudo-terminal (``os.openpty``; the driver opens the
slave path like any serial port) or on a loopback TCP socket (pyserial's
``socket://127.0.0.1:PORT``), with motion that takes time, position limits, echo,
terse and verbose feedback, independent/slaved execution, the power-up banner, the
``!T!T!P!P*`` reset reply, an auxiliary output that switches the laser, and fault
injection: a dropped reply, a command that never answers, a device error, an
unprompted limit hit, and an unplugged cable.

Faults are written ``KIND:COMMAND@N`` and fire on the N-th command (counted from 1)
that starts with COMMAND, e.g. ``unplug:OA1@3`` pulls the cable right after the third
laser-on command is acknowledged; KIND is one of :data:`FAULT_KINDS`.
"""

from __future__ import annotations

import logging
import os
import re
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: drop: executed, reply lost; timeout: not executed, never answered; error: not
#: executed, answered ``! Injected fault``; limit: ``!P`` sent unprompted before the
#: reply; unplug: executed and answered, then the line goes dead for good.
FAULT_KINDS = ("drop", "timeout", "error", "limit", "unplug")

BANNER = "Pan-Tilt Controller v3.02, (C)2024 FLIR Commercial Systems (ilt emulator)\r\nInitializing...\r\n"


@dataclass
class Fault:
    kind: str
    command: str
    nth: int

    @classmethod
    def parse(cls, spec: str) -> Fault:
        m = re.fullmatch(r"\s*(\w+):([A-Za-z0-9+-]+)@(\d+)\s*", spec)
        if not m or m.group(1) not in FAULT_KINDS or int(m.group(3)) < 1:
            raise ValueError(f"fault {spec!r}: expected KIND:COMMAND@N with KIND in {', '.join(FAULT_KINDS)}, N >= 1")
        return cls(m.group(1), m.group(2).upper(), int(m.group(3)))


class _Line:
    """A device on a serial line: transport, echo, byte-wise command parsing, faults.

    Subclasses implement :meth:`handle` (one command, without its delimiter) and
    return the reply text (``"*"``, ``"* value"`` or ``"! message"``).
    """

    def __init__(self, transport: str = "pty", faults=(), banner: str = "", tcp_port: int = 0):
        if transport not in ("pty", "socket"):
            raise ValueError(f"emulator transport {transport!r}: use 'pty' or 'socket'")
        self.transport = transport
        self.faults = [f if isinstance(f, Fault) else Fault.parse(f) for f in faults]
        self.banner = banner
        self.tcp_port = tcp_port
        self.echo = True
        self.counts: dict[str, int] = {}
        self.received: list[str] = []
        self.unplugged = False
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._fd = self._slave = self._server = self._conn = None
        self.port = ""

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> _Line:
        if self.transport == "pty":
            self._fd, self._slave = os.openpty()
            tty.setraw(self._slave)  # the line discipline must not echo or translate
            self.port = os.ttyname(self._slave)
        else:
            self._server = socket.create_server(("127.0.0.1", self.tcp_port))
            self.port = f"socket://127.0.0.1:{self._server.getsockname()[1]}"
        self._thread = threading.Thread(target=self._serve, name=f"emulator {self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._close_all()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def _close_all(self) -> None:
        for name in ("_conn", "_server"):
            s = getattr(self, name)
            if s is not None:
                s.close()
                setattr(self, name, None)
        for name in ("_fd", "_slave"):
            fd = getattr(self, name)
            if fd is not None:
                os.close(fd)
                setattr(self, name, None)

    # -- I/O -------------------------------------------------------------------------
    def _serve(self) -> None:
        buf = b""
        fresh = True
        while not self._stop.is_set() and not self.unplugged:
            data = self._read()
            if data is None:
                buf, fresh = b"", True  # a socket client left; the unit stays powered
                continue
            if not data:
                continue
            if fresh and self.banner:
                self._write(self.banner)
            fresh = False
            if self.echo:
                self._write(data.decode("ascii", "replace"))
            buf += data
            while (m := re.search(rb"[ \r\n]", buf)) is not None:
                token, buf = buf[: m.start()].decode("ascii", "replace").strip(), buf[m.end():]
                if token:
                    self._command(token)
                if self.unplugged or self._stop.is_set():
                    break

    def _read(self) -> bytes | None:
        """Up to 256 bytes, b'' when idle, None when a socket client disconnected."""
        if self.transport == "pty":
            ready, _, _ = select.select([self._fd], [], [], 0.05)
            return os.read(self._fd, 256) if ready else b""
        if self._conn is None:
            ready, _, _ = select.select([self._server], [], [], 0.05)
            if ready:
                self._conn, _ = self._server.accept()
            return b""
        ready, _, _ = select.select([self._conn], [], [], 0.05)
        if not ready:
            return b""
        try:
            data = self._conn.recv(256)
        except OSError:
            data = b""
        if not data:
            self._conn.close()
            self._conn = None
            return None
        return data

    def _write(self, text: str) -> None:
        data = text.encode("ascii")
        try:
            if self.transport == "pty":
                os.write(self._fd, data)
            elif self._conn is not None:
                self._conn.sendall(data)
        except OSError:
            pass  # nobody listening: like a unit talking to an unplugged cable

    def _command(self, token: str) -> None:
        self.received.append(token)
        fault = self._fault_for(token.upper())
        kind = fault.kind if fault else None
        log.debug("emulator %s <- %r%s", self.port, token, f" (fault {kind})" if kind else "")
        if kind == "timeout":
            return
        if kind == "error":
            self._write("! Injected fault\r\n")
            return
        if kind == "limit":
            self._write("!P")
        reply = self.handle(token.upper())
        if kind != "drop":
            self._write(reply + "\r\n")
        if kind == "unplug":
            self.unplug()

    def _fault_for(self, token: str) -> Fault | None:
        hit = None
        for prefix in {f.command for f in self.faults}:
            if token.startswith(prefix):
                self.counts[prefix] = self.counts.get(prefix, 0) + 1
                hit = hit or next((f for f in self.faults if f.command == prefix and f.nth == self.counts[prefix]), None)
        return hit

    def unplug(self) -> None:
        """Pull the cable: the line is dead from now on (the unit keeps its state)."""
        self.unplugged = True
        with self._lock:
            self._close_all()

    def handle(self, token: str) -> str:  # pragma: no cover - abstract
        raise NotImplementedError


class PTUEmulator(_Line):
    """A PTU-D46-like unit. Positions are integer steps; ``resolution`` is arc-seconds
    per step (pan, tilt); ``speed`` steps/s; the aux output is the laser."""

    def __init__(self, transport: str = "pty", *, faults=(), speed: int = 2000,
                 pan_limits=(-3090, 3090), tilt_limits=(-907, 604), resolution=(92.5714, 46.2857),
                 laser_on: str = "OA1", laser_off: str = "OA0", banner: str = BANNER, tcp_port: int = 0):
        super().__init__(transport, faults, banner, tcp_port)
        self.verbose = True
        self.slaved = False
        self.limits = {"PN": pan_limits[0], "PX": pan_limits[1], "TN": tilt_limits[0], "TX": tilt_limits[1]}
        self.resolution = {"P": float(resolution[0]), "T": float(resolution[1])}
        self.speed = {"P": int(speed), "T": int(speed)}
        self.max_speed = 4 * int(speed)
        self._axis = {a: {"from": 0.0, "to": 0.0, "t0": 0.0} for a in "PT"}
        self._pending: dict[str, int] = {}
        self.laser_commands = (laser_on.upper(), laser_off.upper())
        self.aux = False

    # -- truth, for the simulated camera -----------------------------------------------
    def position(self, axis: str) -> float:
        a = self._axis[axis]
        d = a["to"] - a["from"]
        done = min(abs(d), self.speed[axis] * (time.monotonic() - a["t0"]))
        return a["from"] + (done if d >= 0 else -done)

    def pointing(self) -> tuple[float, float, bool]:
        """(pan, tilt) in degrees where the unit really points, and whether the laser is on."""
        return (self.position("P") * self.resolution["P"] / 3600.0,
                self.position("T") * self.resolution["T"] / 3600.0, self.aux)

    def _start(self, axis: str, target: int) -> None:
        now = self.position(axis)
        self._axis[axis] = {"from": now, "to": float(target), "t0": time.monotonic()}

    def _remaining(self) -> float:
        return max((abs(a["to"] - self.position(ax)) / self.speed[ax] for ax, a in self._axis.items()), default=0.0)

    # -- protocol ----------------------------------------------------------------------
    def _ok(self, value=None, verbose_text: str = "") -> str:
        if value is None:
            return "*"
        return f"* {verbose_text}{value}" if self.verbose and verbose_text else f"* {value}"

    def handle(self, token: str) -> str:
        if token in self.laser_commands:
            self.aux = token == self.laser_commands[0]
            return "*"
        m = re.fullmatch(r"([A-Z]+)(-?\d+)?", token)
        if not m:
            return "! Illegal Command"
        cmd, arg = m.group(1), m.group(2)
        value = None if arg is None else int(arg)
        simple = {"ED": ("echo", False), "EE": ("echo", True), "FT": ("verbose", False), "FV": ("verbose", True),
                  "I": ("slaved", False), "S": ("slaved", True)}
        if cmd in simple and value is None:
            setattr(self, *simple[cmd])
            return "*"
        if cmd in ("CI", "LE") and value is None:
            return "*"
        if cmd in ("PP", "TP"):
            axis = cmd[0]
            if value is None:
                return self._ok(round(self.position(axis)), f"Current {'Pan' if axis == 'P' else 'Tilt'} position is ")
            lo, hi = self.limits[axis + "N"], self.limits[axis + "X"]
            name = "Pan" if axis == "P" else "Tilt"
            if value > hi:
                return f"! Maximum allowable {name} position is {hi}"
            if value < lo:
                return f"! Minimum allowable {name} position is {lo}"
            if self.slaved:
                self._pending[axis] = value
            else:
                self._start(axis, value)
            return "*"
        if cmd in ("PS", "TS"):
            if value is None:
                return self._ok(self.speed[cmd[0]], "Target speed is ")
            if not 0 < value <= self.max_speed:
                return f"! Maximum allowable speed is {self.max_speed}"
            self.speed[cmd[0]] = value
            return "*"
        if cmd in self.limits and value is None:
            return self._ok(self.limits[cmd], "Position limit is ")
        if cmd in ("PR", "TR") and value is None:
            return self._ok(f"{self.resolution[cmd[0]]:.4f}", "")
        if cmd == "A" and value is None:
            for axis, target in self._pending.items():
                self._start(axis, target)
            self._pending.clear()
            self._sleep(self._remaining())
            return "*"
        if cmd == "H" and value is None:
            for axis in "PT":
                self._start(axis, round(self.position(axis)))
            return "*"
        if cmd == "R" and value is None:
            self._sleep(0.05)
            for axis in "PT":
                self._axis[axis] = {"from": 0.0, "to": 0.0, "t0": time.monotonic()}
            return "!T!T!P!P*"
        if cmd == "V" and value is None:
            return "* Pan-Tilt Controller v3.02 (ilt emulator)"
        if cmd == self.laser_commands[0][:-1] and value is None:
            return self._ok(int(self.aux))
        return "! Illegal Command"

    def _sleep(self, seconds: float) -> None:
        self._stop.wait(seconds)


class LaserEmulator(_Line):
    """A laser driver on its own serial line: the on/off commands, ``*`` or ``! message``."""

    def __init__(self, transport: str = "pty", *, faults=(), on: str = "L1", off: str = "L0"):
        super().__init__(transport, faults, banner="")
        self.echo = False
        self.commands = (on.upper(), off.upper())
        self.aux = False

    def handle(self, token: str) -> str:
        if token in self.commands:
            self.aux = token == self.commands[0]
            return "*"
        return "! Illegal Command"
