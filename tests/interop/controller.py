"""Another vendor's lift controller for the field gateway tests (crates/canlift/tests/gateway_field.rs):
python-canopen LocalNodes serving the objects of an EDS.

usage: controller.py [--heartbeat MS] HOST PORT EDS NODE [NODE ...]
Each NODE is a LocalNode with the EDS's objects and defaults: it sends its boot-up message, then
heartbeats every MS ms (default 100; also in its 1017h), and goes operational. Prints READY,
then "WRITE NODE INDEX SUB HEXDATA" (index and sub in hex) for every SDO download it accepts;
serves until standard input closes.
"""

import logging
import struct
import sys

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    args = sys.argv[1:]
    heartbeat = 100
    if args[:1] == ["--heartbeat"]:
        heartbeat, args = int(args[1]), args[2:]
    host, port, eds = args[0], int(args[1]), args[2]
    node_ids = [int(n) for n in args[3:]]
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    for node_id in node_ids:
        node = canopen.LocalNode(node_id, eds)

        def written(index, subindex, od, data, node_id=node_id):
            print(f"WRITE {node_id} {index:04X} {subindex:02X} {bytes(data).hex()}", flush=True)

        node.add_write_callback(written)
        network.add_node(node)
        # 1017h as stored, not as written: a write would start heartbeats before the boot-up.
        node.data_store.setdefault(0x1017, {})[0] = struct.pack("<H", heartbeat)
        node.nmt.send_command(0x81)  # reset: the boot-up message
        node.nmt.state = "PRE-OPERATIONAL"  # heartbeats start with 1017h
        node.nmt.state = "OPERATIONAL"
    print("READY", flush=True)
    for _ in sys.stdin:
        pass
    network.disconnect()


if __name__ == "__main__":
    main()
