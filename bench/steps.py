"""The loop's step objects per sample, as the services run them (``python -m bench.steps``).

One 500 Hz lemniscate flown by :func:`tests.loop_replay.messages` gives the messages; each core is then
timed alone on that sequence, fresh for each of 5 repeats (the best repeat counts: these are CPU
costs, and a shared machine only adds to them): the estimator's ``on_state`` + ``on_setpoint`` and
the controller's ``on_state`` + ``on_estimate``, in µs per sample. Messages are decoded before the
clock starts (decoding has its own rows in :mod:`bench.payloads`)."""
from __future__ import annotations

import time

COLUMNS = ("step object, per sample (500 Hz lemniscate)", "best of 5 (µs)", "median of 5 (µs)", "target (µs)")
TARGET_US = 40.0
RATE_HZ, SAMPLES, REPEATS = 500.0, 1500, 5


def _time_estimator(messages) -> float:
    from tests.loop_replay import estimator_core

    core = estimator_core(RATE_HZ, time.monotonic)
    t0 = time.perf_counter()
    for state, _estimate, setpoint in messages:
        core.on_state(state, 0.0)
        core.on_setpoint(setpoint, 0.0)
    return (time.perf_counter() - t0) / len(messages) * 1e6


def _time_controller(messages) -> float:
    from tests.loop_replay import controller_core

    core = controller_core(RATE_HZ, "lemniscate", time.monotonic)
    t0 = time.perf_counter()
    for state, estimate, _setpoint in messages:
        core.on_state(state, 0.0)
        core.on_estimate(estimate, 0.0)
    return (time.perf_counter() - t0) / len(messages) * 1e6


def step_rows(results: dict | None = None) -> list[tuple]:
    import statistics

    from tests.loop_replay import messages as fly

    messages = fly(RATE_HZ, SAMPLES)
    rows = []
    for name, timer in (("estimator: on_state + on_setpoint", _time_estimator),
                        ("controller: on_state + on_estimate", _time_controller)):
        times = [timer(messages) for _ in range(REPEATS)]
        best, median = min(times), statistics.median(times)
        rows.append((name, f"{best:.1f}", f"{median:.1f}", f"≤ {TARGET_US:.0f}"))
        if results is not None:
            results[name.split(":")[0]] = {"best_us": round(best, 1), "median_us": round(median, 1),
                                           "target_us": TARGET_US}
    return rows


if __name__ == "__main__":
    from bench.table import print_table

    print_table(COLUMNS, step_rows())
