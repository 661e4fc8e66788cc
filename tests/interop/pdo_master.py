"""python-canopen's PDO API configuring a canlift LocalNode over SDO
(crates/canopen/tests/python_pdo.rs).

usage: pdo_master.py HOST PORT NODE EDS
TPDO1: 0x2000 event-driven; TPDO2: 0x2001 on every SYNC; RPDO1: 0x2100. Prints CONFIGURED, waits
for TPDO1 to carry 1234, sends RPDO1 = 4321 (RPDO-SENT), sends a SYNC and prints TPDO2's value.
"""

import logging
import sys
import time

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, node_id, eds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    node = canopen.RemoteNode(node_id, eds)
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    node.tpdo.read()
    node.rpdo.read()

    t1 = node.tpdo[1]
    t1.clear()
    t1.add_variable(0x2000)
    t1.trans_type = 254
    t1.event_timer = 0
    t1.enabled = True
    t2 = node.tpdo[2]
    t2.clear()
    t2.add_variable(0x2001)
    t2.trans_type = 1
    t2.enabled = True
    node.tpdo.save()
    r1 = node.rpdo[1]
    r1.clear()
    r1.add_variable(0x2100)
    r1.trans_type = 255
    r1.enabled = True
    node.rpdo.save()
    node.nmt.state = "OPERATIONAL"
    print("CONFIGURED", flush=True)

    deadline = time.time() + 5
    value = None
    while time.time() < deadline and value != 1234:
        t1.wait_for_reception(1)
        value = t1[0].raw
    print("TPDO1", value, flush=True)

    r1[0].raw = 4321
    r1.transmit()
    print("RPDO-SENT", flush=True)

    time.sleep(0.1)
    network.sync.transmit()
    t2.wait_for_reception(2)
    print("TPDO2", t2[0].raw, flush=True)
    network.disconnect()
    print("OK", flush=True)


if __name__ == "__main__":
    main()
