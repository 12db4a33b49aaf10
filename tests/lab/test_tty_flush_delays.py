"""``benchmarks/tty_flush_delays.py`` reads ``perf script`` text: the queue-to-start delay of
each run of a work function, what each CPU ran while the longest waited, and the events perf
lost."""

# ruff: noqa: E501  (the traces hold perf's own lines, whole)
from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.tty_flush_delays import (
    cpu_time,
    main,
    parse,
    quantile,
    summary,
    work_delays,
    worst_report,
)

# The format of ``perf script --show-lost-events -F comm,tid,cpu,time,event,trace`` (lines as
# perf 6.x prints them; thread names may hold spaces). A flush is queued at 10.000, its worker
# woken on CPU 0, migrated to CPU 1 and started at 10.300; a second run waits 0.1 ms; another
# function's work is timed apart. CPU 0 switches twice before the window, CPU 2 first inside it.
TRACE = """\
         python3   501 [000]    9.800000:                sched:sched_switch: prev_comm=swapper/0 prev_pid=0 prev_prio=120 prev_state=R ==> next_comm=python3 next_pid=501 next_prio=120
         python3   501 [000]    9.900000:                sched:sched_switch: prev_comm=python3 prev_pid=501 prev_prio=120 prev_state=S ==> next_comm=burner one next_pid=700 next_prio=120
         python3   501 [001]    9.950000:                sched:sched_switch: prev_comm=swapper/1 prev_pid=0 prev_prio=120 prev_state=R ==> next_comm=python3 next_pid=501 next_prio=120
 board writer 500 [000]   10.000000:    workqueue:workqueue_queue_work: work struct=0xffff1 function=flush_to_ldisc workqueue=events_unbound req_cpu=256 cpu=-1
 board writer 500 [000]   10.000010:          sched:sched_waking: comm=kworker/u8:1 pid=42 prio=120 target_cpu=000
 board writer 500 [000]   10.000012:          sched:sched_wakeup: comm=kworker/u8:1 pid=42 prio=120 target_cpu=000
 board writer 500 [000]   10.002000:    workqueue:workqueue_queue_work: work struct=0xffff2 function=vmstat_update workqueue=events req_cpu=0 cpu=0
       swapper     0 [002]   10.050000:                sched:sched_switch: prev_comm=swapper/2 prev_pid=0 prev_prio=120 prev_state=R ==> next_comm=burner three next_pid=702 next_prio=120
         python3   501 [001]   10.100000:                sched:sched_switch: prev_comm=python3 prev_pid=501 prev_prio=89 prev_state=S ==> next_comm=burner two next_pid=701 next_prio=120
     migration/1    19 [001]   10.200000:          sched:sched_migrate_task: comm=kworker/u8:1 pid=42 prio=120 orig_cpu=0 dest_cpu=1
       burner two   701 [001]   10.300000:                sched:sched_switch: prev_comm=burner two prev_pid=701 prev_prio=120 prev_state=R ==> next_comm=kworker/u8:1 next_pid=42 next_prio=120
  kworker/u8:1-fl    42 [001]   10.300010:  workqueue:workqueue_execute_start: work struct 0xffff1: function flush_to_ldisc
  kworker/u8:1-fl    42 [001]   10.300050:  workqueue:workqueue_execute_start: work struct 0xffff2: function vmstat_update
 board writer 500 [000]   10.400000:    workqueue:workqueue_queue_work: work struct=0xffff1 function=flush_to_ldisc workqueue=events_unbound req_cpu=256 cpu=-1
  kworker/u8:1-fl    42 [001]   10.400100:  workqueue:workqueue_execute_start: work struct 0xffff1: function flush_to_ldisc
 a line perf prints that is not an event
"""

# A run whose span holds a lost-events record, and a queueing whose start was lost (the next
# queueing of the same work comes with no start between: the kernel traces a queueing only
# when the work is not pending).
TRACE_LOSS = """\
 board writer 500 [000]   20.000000:    workqueue:workqueue_queue_work: work struct=0xffff1 function=flush_to_ldisc workqueue=events_unbound req_cpu=256 cpu=-1
          python  24741 [001]   20.100000: PERF_RECORD_LOST lost 7
  kworker/u8:1-fl    42 [001]   20.900000:  workqueue:workqueue_execute_start: work struct 0xffff1: function flush_to_ldisc
 board writer 500 [000]   21.000000:    workqueue:workqueue_queue_work: work struct=0xffff1 function=flush_to_ldisc workqueue=events_unbound req_cpu=256 cpu=-1
 board writer 500 [000]   21.100000:    workqueue:workqueue_queue_work: work struct=0xffff1 function=flush_to_ldisc workqueue=events_unbound req_cpu=256 cpu=-1
  kworker/u8:1-fl    42 [001]   21.150000:  workqueue:workqueue_execute_start: work struct 0xffff1: function flush_to_ldisc
"""


def test_each_run_pairs_with_its_queueing() -> None:
    events = parse(TRACE.splitlines())
    work = work_delays(events, "flush_to_ldisc")
    assert [round(d.wait_s * 1e3, 3) for d in work.delays] == [300.01, 0.1]
    assert work.delays[0].queued_by == "board writer/500"
    assert (work.delays[0].worker, work.delays[0].worker_tid) == ("kworker/u8:1-fl", 42)
    assert (work.unstarted, work.lost_events, work.clean) == (0, 0, work.delays)
    other = work_delays(events, "vmstat_update")
    assert [round(d.wait_s * 1e3, 3) for d in other.delays] == [298.05]
    assert summary(work, over_ms=50.0) == (
        "2 runs; queue to start p50 0.100 ms, p99 300.01 ms, max 300.0 ms; 1 over 50 ms")


def test_a_run_spanning_lost_events_is_left_out_and_a_lost_start_counted() -> None:
    work = work_delays(parse(TRACE_LOSS.splitlines()), "flush_to_ldisc")
    assert [d.spans_loss for d in work.delays] == [True, False]
    # the second run counts from the latest queueing, not the one whose start was lost
    assert [round(d.wait_s * 1e3, 3) for d in work.clean] == [50.0]
    assert (work.unstarted, work.lost_events) == (1, 7)
    assert summary(work, over_ms=50.0) == (
        "1 runs; queue to start p50 50.000 ms, p99 50.00 ms, max 50.0 ms; 0 over 50 ms; "
        "perf lost 7 events, 1 runs spanning a loss left out, 1 starts lost")
    assert summary(work_delays([], "flush_to_ldisc"), over_ms=50.0) == (
        "no runs of the work function in the trace")


def test_quantile_is_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert [quantile(values, q) for q in (0.01, 0.5, 0.99, 1.0)] == [1.0, 50.0, 99.0, 100.0]
    assert quantile([3.0], 0.99) == 3.0
    assert quantile([1.0, 2.0, 3.0], 0.5) == 2.0


def test_fields_keep_thread_names_with_spaces() -> None:
    switch = parse(TRACE.splitlines())[1]
    assert (switch.comm, switch.tid, switch.cpu, switch.t) == ("python3", 501, 0, 9.9)
    assert switch.fields["next_comm"] == "burner one"
    assert switch.fields["prev_state"] == "S"
    lost = parse(TRACE_LOSS.splitlines())[1]
    assert (lost.name, lost.cpu, lost.t, lost.fields) == ("lost", 1, 20.1, {"lost": "7"})


def test_cpu_time_counts_to_the_window_edges() -> None:
    ran = cpu_time(parse(TRACE.splitlines()), 10.0, 10.3)
    # CPU 0: burner one from before the window to its end (python3 ran only before it);
    # CPU 1: python3 until 10.1, then burner two until the worker took the CPU at 10.3;
    # CPU 2: idle until its first switch at 10.05, then burner three
    assert ran == pytest.approx({(0, "burner one/700 prio 120"): 0.3,
                                 (1, "python3/501 prio 120"): 0.1,
                                 (1, "burner two/701 prio 120"): 0.2,
                                 (2, "swapper/2/0 prio 120"): 0.05,
                                 (2, "burner three/702 prio 120"): 0.25})


def test_the_worst_report_shows_the_workers_wakeup_migration_and_what_ran() -> None:
    events = parse(TRACE.splitlines())
    lines = worst_report(events, work_delays(events, "flush_to_ldisc").clean)
    assert lines[0].startswith("longest: 300.0 ms, queued at 10.000000 by board writer/500")
    assert any("sched_waking" in ln and "pid=42" in ln for ln in lines)
    assert any("sched_wakeup" in ln and "target_cpu=000" in ln for ln in lines)
    assert any("sched_migrate_task" in ln and "dest_cpu=1" in ln for ln in lines)
    assert lines[-5:] == ["  cpu 0 burner one/700 prio 120: 300.0",
                          "  cpu 2 burner three/702 prio 120: 250.0",
                          "  cpu 1 burner two/701 prio 120: 200.0",
                          "  cpu 1 python3/501 prio 120: 100.0",
                          "  cpu 2 swapper/2/0 prio 120: 50.0"]


def test_a_file_that_is_no_perf_trace_is_refused_with_its_name(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "not-a-trace.data"
    bad.write_text("garbage\n")
    with pytest.raises(SystemExit) as exit_info:
        main([str(bad)])
    assert exit_info.value.code == 2
    # perf's own reason where perf is installed, or that it is not
    assert f"error: cannot read {bad}" in capsys.readouterr().err
