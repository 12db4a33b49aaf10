#!/bin/bash
# once the local station runs, put its main thread (the asyncio event loop) under SCHED_FIFO $1
PRIO=$1
for i in $(seq 120); do P=$(pgrep -f "lab.cli --log-level INFO local" | head -1); [ -n "$P" ] && break; sleep 0.5; done
sleep 2
chrt -f -p $PRIO $P
for t in /proc/$P/task/*; do echo $(basename $t) $(chrt -p $(basename $t) | head -1 | awk '{print $NF}'); done
