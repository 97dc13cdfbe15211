"""Why a sample was late: a real-time source's deadline misses explained by the loop's own stamps.

The source publishes state ``k`` (stamp ``S``); the estimator publishes its estimate (``E``, in
the setpoint as ``estimate_stamp_s``); the controller publishes the setpoint (``P``); the source
receives it (``R``). A miss is a setpoint not there at the source's next tick (the deadline
``D``). When it comes late, :class:`DeadlineWatch` splits its path into the estimator's share
(``E − S``: bus and estimator), the controller's (``P − E``: bus and controller) and the way
back (``R − P``), and blames the largest. One that never comes: skipped, if a newer setpoint
came on the controller's local ESO (the estimator did not answer), else lost on the bus. The
misses are summed up in one text (the first at once, then at most one per ``report_period_s``)
with their sample numbers, the worst one, the machine's load and a hint, so an operator can tell
a loaded machine (every stage a little late, load above the cores) from a fault (the estimator
silent, or one process late on a quiet machine).

Pure (times are the caller's monotonic seconds, the load is passed in).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from runtime.schema import SetpointMsg

STAGES = ("estimator", "controller", "bus back", "lost")
_WHERE = {"estimator": "estimator", "controller": "controller", "bus back": "bus (setpoint → source)",
          "lost": "bus (setpoints lost)"}


@dataclass(frozen=True)
class Miss:
    """One explained miss. Times in ms; ``late_ms``: after the deadline (None: never answered).
    ``skipped``: never answered because the controller, tired of waiting for the estimator,
    answered a newer sample on its local ESO."""

    seq: int
    late_ms: float | None
    estimator_ms: float | None = None  # state published → estimate published
    controller_ms: float | None = None  # estimate published → setpoint published (None: local ESO flew)
    back_ms: float | None = None  # setpoint published → received by the source
    skipped: bool = False

    @property
    def stage(self) -> str:
        if self.skipped or (self.late_ms is not None and self.controller_ms is None):
            return "estimator"
        if self.late_ms is None:
            return "lost"
        shares = {"estimator": self.estimator_ms, "controller": self.controller_ms, "bus back": self.back_ms}
        return max(shares, key=lambda k: shares[k])

    @property
    def local_eso(self) -> bool:
        """The estimator did not answer in time: the controller flew (or skipped to) its local ESO."""
        return self.skipped or (self.late_ms is not None and self.controller_ms is None)

    def text(self) -> str:
        if self.skipped:
            return (f"sample {self.seq}: never answered — no estimate came, the controller answered a newer "
                    "sample on its local ESO")
        if self.late_ms is None:
            return f"sample {self.seq}: its setpoint never arrived (lost on the bus)"
        if self.controller_ms is None:
            path = f"no estimate in time: state → setpoint {self.estimator_ms:.1f} ms on the controller's local ESO"
        else:
            path = (f"estimator {self.estimator_ms:.1f} ms (state → estimate), controller {self.controller_ms:.1f} ms "
                    "(estimate → setpoint)")
        return f"sample {self.seq}: setpoint {self.late_ms:.1f} ms after the deadline — {path}, bus back {self.back_ms:.1f} ms"


def seq_ranges(seqs) -> str:
    """Sample numbers as sorted ranges: ``[3, 1, 2, 7]`` → ``"1–3, 7"``."""
    runs: list[list[int]] = []
    for k in sorted(set(seqs)):
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}–{b}" for a, b in runs)


@dataclass
class _Pending:
    seq: int
    state_stamp_s: float
    deadline_s: float


class DeadlineWatch:
    """Feed :meth:`missed` at the source's tick, :meth:`arrived` with every setpoint; :meth:`report`
    returns a summary text when there were misses: the first at once, then at most one per
    ``report_period_s``."""

    def __init__(self, *, report_period_s: float = 1.0, lost_after: int = 5) -> None:
        self.report_period_s = report_period_s
        self.lost_after = lost_after
        self.count = 0  # misses since start
        self._pending: dict[int, _Pending] = {}
        self._explained: list[Miss] = []
        self._last_report_s: float | None = None

    def missed(self, seq: int, state_stamp_s: float, deadline_s: float) -> None:
        """No setpoint for sample ``seq`` (published at ``state_stamp_s``) by ``deadline_s``."""
        self.count += 1
        self._pending[seq] = _Pending(seq, state_stamp_s, deadline_s)
        for old in [s for s in self._pending if s <= seq - self.lost_after]:
            self._explained.append(Miss(old, None))
            del self._pending[old]

    def arrived(self, sp: SetpointMsg, received_s: float) -> None:
        p = self._pending.pop(sp.seq, None)
        for older in [s for s in self._pending if s < sp.seq]:  # overtaken: never answered, or lost
            self._explained.append(Miss(older, None, skipped=sp.estimate_stamp_s == 0))
            del self._pending[older]
        if p is None:
            return
        if sp.estimate_stamp_s > 0:
            est, ctl = sp.estimate_stamp_s - p.state_stamp_s, sp.stamp_s - sp.estimate_stamp_s
        else:
            est, ctl = sp.stamp_s - p.state_stamp_s, None
        self._explained.append(Miss(sp.seq, (received_s - p.deadline_s) * 1e3, est * 1e3,
                                    None if ctl is None else ctl * 1e3, (received_s - sp.stamp_s) * 1e3))

    def report(self, now_s: float, *, load_1min: float, cores: int) -> str | None:
        """The misses explained since the last report (at most one text per ``report_period_s``)."""
        if not self._explained or (self._last_report_s is not None
                                   and now_s - self._last_report_s < self.report_period_s):
            return None
        span = None if self._last_report_s is None else now_s - self._last_report_s
        self._last_report_s = now_s
        misses, self._explained = self._explained, []
        by_stage = Counter(m.stage for m in misses)
        worst = max(misses, key=lambda m: float("inf") if m.late_ms is None else m.late_ms)
        load = f"load {load_1min:.2f} on {cores} cores"
        if any(m.local_eso for m in misses):
            verdict = f"the estimator did not answer in time (the controller flew its local ESO; {load}): see its health"
        elif load_1min >= cores:
            verdict = f"machine busy ({load}): likely load, not a fault"
        else:
            verdict = f"machine not busy ({load}): look at the {_WHERE[by_stage.most_common(1)[0][0]]}"
        stages = ", ".join(f"{k} {n}" for k, n in by_stage.most_common())
        return (f"{len(misses)} deadline miss{'es' if len(misses) > 1 else ''}"
                f"{'' if span is None else f' in the last {span:.1f} s'} "
                f"at sample{'s' if len(misses) > 1 else ''} {seq_ranges(m.seq for m in misses)} "
                f"(late in: {stages}); worst {worst.text()}; {verdict}")
