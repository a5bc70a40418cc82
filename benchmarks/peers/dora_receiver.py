"""dora node: take ``now − stamp`` of every sample and its arrival time (bench_peers.py)."""

import os
import sys
import time

import numpy as np
from dora import Node

cycles, cpu, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
os.sched_setaffinity(0, {cpu})
hops = np.zeros(cycles, dtype=np.int64)
arrivals = np.zeros(cycles, dtype=np.int64)
node = Node()
received = 0
for event in node:
    if event["type"] != "INPUT":
        continue
    now = time.monotonic_ns()
    hops[received] = now - event["value"][0].as_py()
    arrivals[received] = now
    received += 1
    if received == cycles:
        break
np.savez(out, hops=hops[:received], arrivals=arrivals[:received])
