"""python-can side of canlift's interop tests (driven by crates/canbus/tests/python_can.rs).

Frame i of the pattern: every third frame has a 29-bit ID, lengths cycle 0..8. The Rust tests
compute the same sequence (crates/canbus/tests/common/mod.rs, `pattern`).

usage: pattern.py send|recv|loop HOST PORT CHANNEL COUNT
  send  send COUNT pattern frames, then exit
  recv  print READY once on the bus, receive COUNT frames, check each, print OK COUNT
  loop  two python-can buses on the channel: one sends, the other receives and checks
"""

import sys
import threading

import logging

import can

logging.getLogger("can").setLevel(logging.ERROR)


def pattern(i):
    length = i % 9
    data = bytes((i * 31 + k * 7) & 0xFF for k in range(length))
    if i % 3 == 0:
        return can.Message(arbitration_id=(i * 2654435761) & 0x1FFFFFFF, data=data, is_extended_id=True)
    return can.Message(arbitration_id=(i * 7919) % 0x800, data=data, is_extended_id=False)


def open_bus(host, port, channel):
    return can.Bus(interface="socketcand", host=host, port=port, channel=channel, tcp_tune=True)


def send(bus, count):
    for i in range(count):
        bus.send(pattern(i))


def receive(bus, count):
    for i in range(count):
        msg = bus.recv(timeout=20)
        if msg is None:
            sys.exit(f"FAIL: timed out waiting for frame {i}")
        want = pattern(i)
        got = (msg.arbitration_id, msg.is_extended_id, bytes(msg.data), msg.dlc)
        expected = (want.arbitration_id, want.is_extended_id, bytes(want.data), want.dlc)
        if got != expected:
            sys.exit(f"FAIL: frame {i}: got {got}, expected {expected}")
    extra = bus.recv(timeout=0.2)
    if extra is not None:
        sys.exit(f"FAIL: unexpected extra frame {extra}")


def main():
    mode, host, port, channel, count = sys.argv[1:6]
    port, count = int(port), int(count)
    if mode == "send":
        bus = open_bus(host, port, channel)
        send(bus, count)
        bus.shutdown()
    elif mode == "recv":
        bus = open_bus(host, port, channel)
        print("READY", flush=True)
        receive(bus, count)
        bus.shutdown()
    elif mode == "loop":
        tx, rx = open_bus(host, port, channel), open_bus(host, port, channel)
        sender = threading.Thread(target=send, args=(tx, count))
        sender.start()
        receive(rx, count)
        sender.join()
        tx.shutdown()
        rx.shutdown()
    else:
        sys.exit(f"unknown mode {mode}")
    print(f"OK {count}", flush=True)


if __name__ == "__main__":
    main()
