"""Bench rows: a recorded flight → trained, certified, promoted network, stage by stage.

Flies the near-ground lemniscate (3 s ramp + 30 s of cycles) through ``neso up`` with the recorder
and trainer on (:func:`cli.demo.fly_tdr_loop`, stopping once the new network flies), ~50 s wall.
The row's figure is from the end of the recording to the first estimate made with the promoted
network, without the 2 s the demo leaves the candidate in shadow; target < 15 s for 30 s of data.
``quick``: 20 training epochs instead of 100 (the flight cannot be shorter: it is the 30 s of data).
"""
from __future__ import annotations

import tempfile

COLUMNS = ("recording → promoted network (30 s of lemniscate data)", "seconds")


def tdr_rows(quick: bool = False) -> list[tuple[str, str]]:
    from cli.demo import fly_tdr_loop, free_loopback_port

    with tempfile.TemporaryDirectory(prefix="neso-bench-tdr-") as workdir:
        report = fly_tdr_loop(hub=f"tcp/127.0.0.1:{free_loopback_port()}", workdir=workdir,
                              epochs=20 if quick else 100, log=lambda *_: None, fly_after=False)
    s = report.stage_s
    total = s["recording stopped -> promoted (without the 2 s shadow)"]
    rows = [(f"recording stopped → promoted, total (target < 15 s){' [--quick: 20 epochs]' if quick else ''}",
             f"{total:.2f}")]
    for key in ("stop recording", "trainer dataset", "trainer train", "trainer certify", "trainer store",
                "trainer offer", "promote"):
        if key in s:
            rows.append((f"  {key.replace('trainer ', '')}", f"{s[key]:.2f}"))
    return rows
