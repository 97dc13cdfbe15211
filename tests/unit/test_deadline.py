"""A deadline miss explained: which process took the time, how late, load or fault."""
from __future__ import annotations

from runtime.schema import SetpointMsg
from flight.deadline import DeadlineWatch, Miss, seq_ranges
from tests.helpers import named_samples


def setpoint(seq, *, state_s, estimate_s, published_s):
    return SetpointMsg(seq=seq, stamp_s=published_s, state_stamp_s=state_s, t_s=0.02 * seq, roll_rad=0.0,
                       pitch_rad=0.0, yaw_rad=0.0, thrust_norm=0.5, thrust_n=9.8, acc_cmd_enu_mps2=(0.0, 0.0, 0.0),
                       estimate_source="estimator" if estimate_s else "local_eso", estimate_stamp_s=estimate_s)


def test_a_late_setpoint_is_split_into_the_estimators_the_controllers_and_the_way_back():
    w = DeadlineWatch()
    w.missed(10, state_stamp_s=100.000, deadline_s=100.020)
    w.arrived(setpoint(10, state_s=100.000, estimate_s=100.025, published_s=100.026), received_s=100.027)
    text = w.report(100.03, load_1min=0.4, cores=2)  # the first at once
    assert text.startswith("1 deadline miss at sample 10 (late in: estimator 1); worst sample 10: setpoint "
                           "7.0 ms after the deadline — estimator 25.0 ms (state → estimate), controller 1.0 ms "
                           "(estimate → setpoint), bus back 1.0 ms")
    assert text.endswith("machine not busy (load 0.40 on 2 cores): look at the estimator")
    assert w.count == 1 and w.report(103.0, load_1min=0.4, cores=2) is None, "nothing new: no report"
    w.missed(11, state_stamp_s=103.0, deadline_s=103.02)
    w.arrived(setpoint(11, state_s=103.0, estimate_s=103.001, published_s=103.03), received_s=103.031)
    assert w.report(103.5, load_1min=0.4, cores=2).startswith(
        "1 deadline miss in the last 3.5 s at sample 11 (late in: controller")
    w.missed(12, state_stamp_s=103.5, deadline_s=103.52)
    w.arrived(setpoint(12, state_s=103.5, estimate_s=103.501, published_s=103.53), received_s=103.531)
    assert w.report(104.0, load_1min=0.4, cores=2) is None, "at most one report a second"
    assert w.report(104.6, load_1min=0.4, cores=2)


def test_many_misses_on_a_busy_machine_read_as_load_and_lost_ones_are_counted():
    w = DeadlineWatch()
    for k in range(3):
        w.missed(k, state_stamp_s=k * 0.02, deadline_s=k * 0.02 + 0.02)
    w.arrived(setpoint(1, state_s=0.02, estimate_s=0.021, published_s=0.050), received_s=0.051)  # 0 overtaken
    w.arrived(setpoint(2, state_s=0.04, estimate_s=0.039, published_s=0.045), received_s=0.071)  # slow way back
    w.missed(20, state_stamp_s=0.4, deadline_s=0.42)  # never answered ...
    for k in range(21, 26):
        w.missed(k, state_stamp_s=k * 0.02, deadline_s=k * 0.02 + 0.02)  # ... 5 samples later: lost
    text = w.report(1.0, load_1min=3.0, cores=2)
    assert text.startswith("4 deadline misses at samples 0–2, 20 (late in: lost 2, controller 1, bus back 1); "
                           "worst sample 0: its setpoint never arrived (lost on the bus)")
    assert text.endswith("machine busy (load 3.00 on 2 cores): likely load, not a fault")
    assert w.count == 9


def test_an_estimator_that_stops_answering_is_named_whatever_the_load():
    """kill -9 of the estimator: the controller waits 3 periods, then answers the newest sample on
    its local ESO; the samples it skipped and the one it answered late are the estimator's."""
    w = DeadlineWatch()
    for k in (100, 101, 102):
        w.missed(k, state_stamp_s=k * 0.02, deadline_s=k * 0.02 + 0.02)
    w.arrived(setpoint(102, state_s=2.04, estimate_s=0.0, published_s=2.061), received_s=2.062)
    text = w.report(3.0, load_1min=3.0, cores=2)
    assert text.startswith("3 deadline misses at samples 100–102 (late in: estimator 3); worst sample 100: never "
                           "answered — no estimate came, the controller answered a newer sample on its local ESO")
    assert text.endswith("the estimator did not answer in time (the controller flew its local ESO; load 3.00 on "
                         "2 cores): see its health")
    late = Miss(102, late_ms=2.0, estimator_ms=21.0, controller_ms=None, back_ms=1.0)
    assert late.stage == "estimator" and late.text() == (
        "sample 102: setpoint 2.0 ms after the deadline — no estimate in time: state → setpoint 21.0 ms on the "
        "controller's local ESO, bus back 1.0 ms")


def test_the_missed_samples_are_named_as_ranges_and_the_tests_read_them_back():
    assert seq_ranges([7, 3, 1, 2, 2]) == "1–3, 7" and seq_ranges([5]) == "5" and seq_ranges([]) == ""
    watch = DeadlineWatch()
    for seq in (280, 281, 282, 283, 291):
        watch.missed(seq, state_stamp_s=0.02 * seq, deadline_s=0.02 * seq + 0.015)
    watch.arrived(setpoint(292, state_s=5.84, estimate_s=5.841, published_s=5.842), received_s=5.843)
    text = watch.report(6.0, load_1min=3.0, cores=2)
    assert named_samples(text) == {280, 281, 282, 283, 291}, text
    assert named_samples("rigid body 'uav1' lost") == set()
