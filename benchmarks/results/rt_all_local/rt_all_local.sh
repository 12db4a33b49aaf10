#!/bin/bash
# once the local station runs, put its threads (but the SCHED_FIFO display loop) under SCHED_FIFO $1
PRIO=$1
for i in $(seq 120); do P=$(pgrep -f "lab.cli --log-level INFO local" | head -1); [ -n "$P" ] && break; sleep 0.5; done
sleep 2
for t in /proc/$P/task/*; do tid=$(basename $t); pol=$(chrt -p $tid | head -1 | awk '{print $NF}'); if [ "$pol" != "SCHED_FIFO" ]; then chrt -f -p $PRIO $tid; fi; done
chrt -p $(ls /proc/$P/task | head -1) ; for t in /proc/$P/task/*; do echo $(cat $t/comm) $(chrt -p $(basename $t) | head -1 | awk '{print $NF}'); done
