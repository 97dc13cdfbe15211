"""A real viser server and a client speaking the page's websocket protocol: an update made on another
thread exactly while the page's sender starts to wait (dashboard/viser_threads.py).

With viser's own ``asyncio.Event`` the page never gets another update (what froze a CI page for over a
minute); with :class:`dashboard.viser_threads.LoopEvent` it gets them. The interleaving is forced (the
update runs while the sender's ``wait()`` creates its future), so neither outcome is luck."""
from __future__ import annotations

import asyncio
import time

import pytest

from dashboard.viser_threads import LoopEvent, install
from tests.busutil import free_port
from tests.helpers import race_the_next_wait


def frames_until_quiet(ws, quiet_s: float) -> int:
    """How many frames arrive before ``quiet_s`` passes without one."""
    n = 0
    while True:
        try:
            ws.recv(timeout=quiet_s)
        except TimeoutError:
            return n
        n += 1


@pytest.mark.parametrize("patched", [False, True], ids=["viser's asyncio.Event", "LoopEvent"])
def test_an_update_racing_the_senders_wait(patched):
    import viser
    from websockets.sync.client import connect

    install()
    port = free_port()
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        websock = server._websock_server
        buffer = websock._broadcast_buffer
        assert isinstance(buffer.message_event, LoopEvent)
        if not patched:
            buffer.message_event = asyncio.Event()  # viser 1.1.1 as shipped
        text = server.gui.add_markdown("start")
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            assert frames_until_quiet(ws, 0.5) >= 1  # the page's initial state
            ran = race_the_next_wait(websock._background_event_loop, buffer.message_event,
                                     lambda: setattr(text, "content", "racing"))
            text.content = "wake"  # the sender sends it, then waits again: the race runs there
            assert ran.wait(5.0), "the sender never waited again"
            frames_until_quiet(ws, 0.5)
            for j in range(5):
                text.content = f"after {j}"
                time.sleep(0.05)
            after = frames_until_quiet(ws, 1.5)
        if patched:
            assert after >= 1, "LoopEvent: the page got nothing after the race"
        else:
            assert after == 0, "viser's own event woke the page: the patch may no longer be needed"
    finally:
        server.stop()
