"""The TCP side of PX4's simulator interface: the world listens, PX4 SITL connects (``simulator_mavlink
start -c 4560``: PX4 is the client of localhost:4560 + instance), and every exchange is one
``HIL_SENSOR`` out and one ``HIL_ACTUATOR_CONTROLS`` back (lockstep: PX4's clock is the sensors'
``time_usec``). The one I/O module of ``sim/`` besides ``mavlink_vehicle.py``; ``sim.px4_hil`` uses it
through :meth:`Px4SimLink.exchange`.

As Gazebo Classic's ``mavlink_interface`` does it: until PX4's first actuator message the world does not
wait for one (PX4 is booting), afterwards it waits up to ``reply_timeout_s`` for each. A PX4 that does not
answer within it *stalls* the link: the world stops waiting for it (the motors go off, as ESCs do without their
autopilot's signal) and sends its next sensors, and lockstep resumes at PX4's next answer. The connection is
kept: PX4 SITL connects once at boot and never again, so dropping it made a passing stall permanent (on a
loaded machine PX4 once waited for the world's next sensors while the world waited for its answer, both ~1 s;
the world dropped the link and PX4 froze for good). A PX4 that closes the connection (killed, crashed) is
dropped, and the link accepts the next PX4 that connects.
"""
from __future__ import annotations

import select
import socket
import time

from pymavlink.dialects.v20 import common as mavlink2

from sim.px4_hil import HilSensor


class Px4SimLink:
    """``exchange(sensor)`` → PX4's 16 actuator outputs, or None (no PX4, or it did not answer).

    An answer is PX4's first actuator message stamped at or after the sensors' ``time_usec`` (PX4 stamps it with
    its lockstep clock, which the sensors set): one stamped earlier answers sensors sent before (sent while the world
    was not waiting, at boot or after a stall) and is skipped, so the world never flies one exchange behind.

    Counters: ``sent`` sensors, ``received`` actuator messages, ``stale`` of them skipped as answers to earlier
    sensors, ``connections`` accepted, ``dropped`` connections closed or failed, ``stalls`` times PX4 did not
    answer within ``reply_timeout_s``; ``heartbeat`` the newest HEARTBEAT PX4 sent here (its armed flag in
    ``base_mode``), ``last_text`` its newest STATUSTEXT on this link. ``connect_log(level, line)`` hears of every
    connect, stall, resumption and drop (``level`` ``"info"``, or ``"warning"`` for a stall or a drop)."""

    def __init__(self, port: int = 4560, *, host: str = "127.0.0.1", reply_timeout_s: float = 1.0,
                 connect_log=None) -> None:
        self.address = (host, port)
        self.reply_timeout_s = reply_timeout_s
        self.log = connect_log or (lambda level, line: None)
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(self.address)
        self._server.listen(1)
        self._server.setblocking(False)
        self._conn: socket.socket | None = None
        self._mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=0)
        self._parser = mavlink2.MAVLink(None)
        self._answering = False  # PX4 has sent its first HIL_ACTUATOR_CONTROLS on this connection
        self._controls: tuple[float, ...] | None = None
        self.sent = self.received = self.stale = self.connections = self.dropped = self.stalls = 0
        self._sent_usec = 0  # the newest sensors' time_usec: answers stamped before it are stale
        self._stalled_at_s: float | None = None  # time.monotonic() of the stall PX4 has not yet answered after
        self.heartbeat = None
        self.last_text = ""

    @property
    def connected(self) -> bool:
        return self._conn is not None

    def exchange(self, sensor: HilSensor) -> tuple[float, ...] | None:
        if self._conn is None and not self._accept():
            return None
        msg = self._mav.hil_sensor_encode(
            sensor.time_usec, *sensor.acc_frd_mps2, *sensor.gyro_frd_rps, *sensor.mag_frd_gauss,
            sensor.abs_pressure_hpa, 0.0, sensor.pressure_alt_m, sensor.temperature_c, sensor.fields_updated, 0)
        try:
            self._conn.sendall(msg.pack(self._mav))
        except OSError as exc:
            self._drop(f"send failed: {exc}")
            return None
        self.sent += 1
        self._sent_usec = sensor.time_usec
        self._controls = None
        start = time.monotonic()
        while self._controls is None and self._conn is not None:
            # waiting only while PX4 answers (a late answer to earlier sensors says it does again)
            deadline = start + (self.reply_timeout_s if self._answering else 0.0)
            wait = max(0.0, deadline - time.monotonic())
            if not self._read(wait) and time.monotonic() >= deadline:
                break
        if self._controls is None and self._answering:
            self._stall()
        return self._controls

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        self._server.close()

    # -- internals -------------------------------------------------------------------------
    def _accept(self) -> bool:
        try:
            conn, peer = self._server.accept()
        except BlockingIOError:
            return False
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn, self._answering = conn, False
        self._parser = mavlink2.MAVLink(None)
        self.connections += 1
        self.log("info", f"PX4 connected from {peer[0]}:{peer[1]}")
        return True

    def _read(self, timeout_s: float) -> bool:
        """Read what has arrived (waiting up to ``timeout_s`` for something); True if anything did."""
        ready, _, _ = select.select([self._conn], [], [], timeout_s)
        if not ready:
            return False
        try:
            data = self._conn.recv(65536)
        except OSError as exc:
            self._drop(f"receive failed: {exc}")
            return False
        if not data:
            self._drop("PX4 closed the connection")
            return False
        for msg in self._parser.parse_buffer(data) or ():
            kind = msg.get_type()
            if kind == "HIL_ACTUATOR_CONTROLS":
                self._answering = True
                self.received += 1
                if msg.time_usec < self._sent_usec:
                    self.stale += 1
                    continue
                self._controls = tuple(msg.controls)
                if self._stalled_at_s is not None:
                    self.log("info", f"PX4 answers again after {time.monotonic() - self._stalled_at_s:.1f} s: "
                                     "lockstep resumed")
                    self._stalled_at_s = None
            elif kind == "HEARTBEAT":
                self.heartbeat = msg
            elif kind == "STATUSTEXT":
                self.last_text = msg.text
        return True

    def _stall(self) -> None:
        """PX4 did not answer the sensors just sent: no waiting for it until it answers again (the connection kept)."""
        self._answering = False
        self.stalls += 1
        self._stalled_at_s = time.monotonic()
        self.log("warning", f"PX4 not answering (no HIL_ACTUATOR_CONTROLS within {self.reply_timeout_s:.1f} s): "
                            "motors off, the world goes on sending sensors without waiting until PX4 answers again")

    def _drop(self, why: str) -> None:
        if self._conn is not None:
            self._conn.close()
        self._conn, self._answering, self._controls, self._stalled_at_s = None, False, None, None
        self.dropped += 1
        self.log("warning", f"PX4 link dropped ({why}); motors off, waiting for PX4 to connect again")
