"""python-canopen as NMT master and EMCY consumer of a canlift LocalNode
(crates/canopen/tests/python_nmt.rs).

usage: nmt_master.py HOST PORT NODE
Prints READY once connected; then waits for the node's boot-up, commands it through
operational, stopped and pre-operational (reading the state back from its heartbeat each time),
prints WAIT-EMCY and waits for EMCY 0x4210.
"""

import logging
import sys
import threading
import time

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, node_id = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
    network.add_node(node)
    # Listen for the boot-up before announcing READY: the node starts as soon as we do, and
    # wait_for_bootup() would miss a boot-up that arrives before it is called.
    booted = threading.Event()

    def on_error_control(can_id, data, timestamp):
        if len(data) == 1 and data[0] == 0:
            booted.set()

    network.subscribe(0x700 + node_id, on_error_control)
    print("READY", flush=True)
    if not booted.wait(10):
        sys.exit("FAIL: no boot-up message")
    print("BOOTUP", flush=True)
    for state in ["OPERATIONAL", "STOPPED", "PRE-OPERATIONAL"]:
        node.nmt.state = state
        node.nmt.wait_for_heartbeat(2)  # may still carry the old state
        print("HEARTBEAT", node.nmt.wait_for_heartbeat(2), flush=True)
    print("WAIT-EMCY", flush=True)
    # From the consumer's log, not emcy.wait(): wait() sees only what arrives after it is called,
    # and the node may send as soon as it reads WAIT-EMCY.
    deadline = time.monotonic() + 5
    error = None
    while error is None and time.monotonic() < deadline:
        error = next((e for e in list(node.emcy.log) if e.code == 0x4210), None)
        if error is None:
            time.sleep(0.01)
    if error is None:
        sys.exit("FAIL: no EMCY 0x4210")
    print(f"EMCY {error.code:04X} {error.register:02X} {bytes(error.data).hex()}", flush=True)
    network.disconnect()
    print("OK", flush=True)


if __name__ == "__main__":
    main()
