"""Two python-can clients through a hub: the comparison figure for docs/BENCHMARKS.md.

usage: bench_python_can.py HOST PORT FRAMES [RATE]
One client sends FRAMES 8-byte frames (RATE per second, 0 = as fast as python-can sends), the
other receives them; prints frames/s and one-way latency p50/p99 (both clients in this process,
so one clock).
"""

import statistics
import struct
import sys
import threading
import time

import logging

import can

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, frames = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    rate = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    tx = can.Bus(interface="socketcand", host=host, port=port, channel="pybench", tcp_tune=True)
    rx = can.Bus(interface="socketcand", host=host, port=port, channel="pybench", tcp_tune=True)
    time.sleep(0.2)
    start = time.perf_counter_ns()

    def send():
        for i in range(frames):
            if rate:
                due = start + i * 1_000_000_000 // rate
                while time.perf_counter_ns() < due:
                    time.sleep(0.0002)
            now_us = (time.perf_counter_ns() - start) // 1000
            tx.send(can.Message(arbitration_id=0x100, data=struct.pack("<II", i, now_us & 0xFFFFFFFF),
                                is_extended_id=False))

    thread = threading.Thread(target=send)
    thread.start()
    latencies, received = [], 0
    while received < frames:
        msg = rx.recv(timeout=10)
        if msg is None:
            break
        _, sent_us = struct.unpack("<II", msg.data)
        latencies.append((time.perf_counter_ns() - start) // 1000 - sent_us)
        received += 1
    elapsed = (time.perf_counter_ns() - start) / 1e9
    thread.join()
    tx.shutdown()
    rx.shutdown()
    latencies.sort()
    p = lambda q: latencies[min(len(latencies) - 1, round(q * (len(latencies) - 1)))] if latencies else 0
    print(f"python-can -> hub -> python-can: {frames} frames, rate {'flood' if not rate else rate}")
    print(f"  delivered {received}/{frames} in {elapsed:.3f} s = {received / elapsed:.0f} frames/s")
    print(f"  latency: p50 {p(0.5)} us, p99 {p(0.99)} us, max {latencies[-1] if latencies else 0} us")


if __name__ == "__main__":
    main()
