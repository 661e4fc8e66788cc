"""Another vendor's lift controller for the field gateway tests (crates/canlift/tests/gateway_field.rs):
python-canopen LocalNodes serving the objects of an EDS.

usage: controller.py HOST PORT EDS NODE [NODE ...]
Each NODE is a LocalNode with the EDS's objects and defaults, operational, heartbeat 100 ms.
Prints READY, then "WRITE NODE INDEX SUB HEXDATA" (index and sub in hex) for every SDO download
it accepts; serves until standard input closes.
"""

import logging
import sys

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, eds = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    node_ids = [int(n) for n in sys.argv[4:]]
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    for node_id in node_ids:
        node = canopen.LocalNode(node_id, eds)

        def written(index, subindex, od, data, node_id=node_id):
            print(f"WRITE {node_id} {index:04X} {subindex:02X} {bytes(data).hex()}", flush=True)

        node.add_write_callback(written)
        network.add_node(node)
        node.nmt.state = "OPERATIONAL"
        node.nmt.start_heartbeat(100)
    print("READY", flush=True)
    for _ in sys.stdin:
        pass
    network.disconnect()


if __name__ == "__main__":
    main()
