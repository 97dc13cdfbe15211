"""The world's side of PX4's simulator link (sim.px4_link) against a PX4 stand-in on real TCP speaking real
MAVLink 2: one HIL_SENSOR out, its HIL_ACTUATOR_CONTROLS back, stamped with PX4's lockstep clock (the sensors'
``time_usec``) as SimulatorMavlink does. Real PX4 flies through it in tests/px4/."""
from __future__ import annotations

import socket
import threading
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from sim.px4_hil import HilSensor
from sim.px4_link import Px4SimLink
from tests.busutil import free_port

REPLY_TIMEOUT_S = 0.3
T0_USEC, PERIOD_USEC = 1_000_000, 4_000  # the k-th sensors' time_usec: T0_USEC + k · PERIOD_USEC (250 Hz)


class FakePx4:
    """PX4 SITL's simulator client: connects to the world, answers the i-th HIL_SENSOR of its connection with
    ``answers(i, time_usec)`` → the stamps of the HIL_ACTUATOR_CONTROLS it sends back, each carrying in controls[0]
    which sensors it answers (:func:`sensor`'s k of its stamp, / 1000). ``close_after``: the connection closed on
    that sensor, as a killed PX4's is."""

    def __init__(self, port: int, answers, close_after: int | None = None) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as SimulatorMavlink's own socket
        self.answers, self.close_after = answers, close_after
        self._mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        parser, i = mavlink2.MAVLink(None), 0
        with self.sock:
            while True:
                data = self.sock.recv(65536)
                if not data:
                    return
                for msg in parser.parse_buffer(data) or ():
                    if msg.get_type() != "HIL_SENSOR":
                        continue
                    if i == self.close_after:
                        return
                    for stamp in self.answers(i, msg.time_usec):
                        controls = [(stamp - T0_USEC) / PERIOD_USEC / 1000.0] + [0.0] * 15
                        self.sock.sendall(self._mav.hil_actuator_controls_encode(stamp, controls, 0, 0).pack(self._mav))
                    i += 1

    def close(self) -> None:
        """PX4 killed: its connection closed (the thread sees it end)."""
        if self.thread.is_alive():
            self.sock.shutdown(socket.SHUT_RDWR)
        self.thread.join(5)


def sensor(k: int) -> HilSensor:
    return HilSensor(time_usec=T0_USEC + PERIOD_USEC * k, acc_frd_mps2=(0.0, 0.0, -9.81), gyro_frd_rps=(0.0, 0.0, 0.0),
                     mag_frd_gauss=(0.2, 0.0, 0.4), abs_pressure_hpa=1013.0, pressure_alt_m=0.0, temperature_c=20.0,
                     fields_updated=0x1FFF)


@pytest.fixture
def link():
    lines: list[str] = []
    link = Px4SimLink(free_port(), reply_timeout_s=REPLY_TIMEOUT_S, connect_log=lambda _level, line: lines.append(line))
    link.lines = lines
    yield link
    link.close()


def answered(link: Px4SimLink, k: int) -> int | None:
    """Which sensors the answer to the world's exchange of the k-th sensors was for (None: no answer); the world's
    pace, one sensor period each, when it is not waiting for PX4."""
    started = time.monotonic()
    out = link.exchange(sensor(k))
    time.sleep(max(0.0, started + PERIOD_USEC / 1e6 - time.monotonic()))
    return None if out is None else round(out[0] * 1000)


def into_lockstep(link: Px4SimLink, k: int = 0) -> int:
    """Exchanges until one is answered for its own sensors (PX4 booting: the world does not wait yet); the next k."""
    for k in range(k, k + 50):
        if answered(link, k) == k:
            return k + 1
    raise AssertionError(f"never in lockstep: {link.lines}")


def test_each_exchange_takes_the_answer_to_its_own_sensors_never_an_earlier_one(link):
    """PX4 answering every sensor twice, first late for the ones before (as after a boot or a stall, when answers
    to sensors sent without waiting are still on their way): the world skips those and flies no exchange behind."""
    px4 = FakePx4(link.address[1], lambda i, t: [t - PERIOD_USEC, t] if i else [t])
    k = into_lockstep(link)
    assert [answered(link, j) for j in range(k, k + 20)] == list(range(k, k + 20))
    assert link.stale >= 20 and link.stalls == 0 and link.dropped == 0
    px4.close()


def test_a_px4_that_stops_answering_stalls_the_link_and_lockstep_resumes_on_the_same_connection(link):
    """PX4 leaves one sensors unanswered and waits for the next (on a loaded machine real PX4 did: 'poll timeout',
    ~1 s, while the world waited for its answer). Before: the world dropped the connection after reply_timeout_s;
    PX4 SITL never connects again, so PX4 froze for good and every later test on that vehicle failed."""
    stall_at = 30
    px4 = FakePx4(link.address[1], lambda i, t: [] if i == stall_at else [t])
    k = into_lockstep(link)
    assert k <= stall_at
    assert [answered(link, j) for j in range(k, stall_at)] == list(range(k, stall_at))
    assert answered(link, stall_at) is None, "an unanswered exchange: motors off"
    assert link.stalls == 1 and link.dropped == 0 and link.connections == 1 and link.connected
    assert any("PX4 not answering" in line for line in link.lines), link.lines
    k = into_lockstep(link, stall_at + 1)
    assert k <= stall_at + 5, "back in lockstep within a few sensor periods"
    assert [answered(link, j) for j in range(k, k + 20)] == list(range(k, k + 20))
    assert link.stalls == 1 and link.dropped == 0 and link.connections == 1
    assert any("PX4 answers again after" in line for line in link.lines), link.lines
    px4.close()


def test_a_px4_that_closes_the_connection_is_dropped_and_the_next_one_accepted(link):
    first = FakePx4(link.address[1], lambda i, t: [t], close_after=8)
    k = into_lockstep(link)
    for j in range(k, 20):
        if answered(link, j) is None and not link.connected:
            break
    assert link.dropped == 1 and link.stalls == 0 and not link.connected, link.lines
    assert any("PX4 closed the connection" in line for line in link.lines), link.lines
    first.close()
    second = FakePx4(link.address[1], lambda i, t: [t if i else T0_USEC])  # its first answer stale, as at a boot
    k = into_lockstep(link, 100)
    assert link.connections == 2 and answered(link, k) == k
    second.close()
