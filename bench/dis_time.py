#!/usr/bin/env python3
"""Time OpenCV's DIS optical flow (preset ultrafast) on one image pair, the way
`flownav flow A B --json --repeat N` times flownav: one uncounted call, then N timed calls.

Usage: python3 bench/dis_time.py A.png B.png THREADS N
(`pip install opencv-python-headless`.) Prints one JSON line: wall min / median / p90 ms per
pair and the process CPU time; run it beside `flownav flow A B --json --repeat N --threads
THREADS` on the same machine, interleaved, and compare.
"""
import cv2, sys, time, json, statistics
a = cv2.imread(sys.argv[1], cv2.IMREAD_GRAYSCALE); b = cv2.imread(sys.argv[2], cv2.IMREAD_GRAYSCALE)
threads = int(sys.argv[3]); n = int(sys.argv[4])
cv2.setNumThreads(threads)
dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
dis.calc(a, b, None)
wall = []; cpu = []
for _ in range(n):
    t0 = time.perf_counter(); c0 = time.process_time()
    dis.calc(a, b, None)
    wall.append((time.perf_counter() - t0) * 1e3); cpu.append((time.process_time() - c0) * 1e3)
wall.sort(); cpu.sort()
print(json.dumps({"tool": "opencv-dis-ultrafast", "threads": threads, "min_ms": wall[0], "median_ms": statistics.median(wall), "p90_ms": wall[int(0.9 * n) - 1], "cpu_min_ms": cpu[0], "cpu_median_ms": statistics.median(cpu), "opencv": cv2.__version__}))
