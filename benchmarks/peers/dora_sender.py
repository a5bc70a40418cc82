"""dora node: on each timer tick, send the CLOCK_MONOTONIC time it was sent at (bench_peers.py)."""

import os
import sys
import time

import numpy as np
import pyarrow as pa
from dora import Node

cycles, cpu, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
os.sched_setaffinity(0, {cpu})
ticks = np.zeros(cycles, dtype=np.int64)
node = Node()
sent = 0
for event in node:
    if event["type"] != "INPUT":
        continue
    now = time.monotonic_ns()
    ticks[sent] = now
    node.send_output("stamp", pa.array([now], type=pa.int64()))
    sent += 1
    if sent == cycles:
        break
np.save(out, ticks[:sent])
