"""A python-canopen LocalNode for canlift's SDO client (crates/canopen/tests/python_canopen.rs).

usage: local_node.py HOST PORT NODE
Objects: 0x1008 VISIBLE_STRING ro "python-canopen", 0x1017 UNSIGNED16 rw (heartbeat 100 ms,
running), 0x2000 DOMAIN rw, 0x2001 UNSIGNED32 rw, 0x2002 INTEGER16 rw. The node follows NMT
commands. Prints READY, serves until standard input closes; a line "emcy CODE" on standard input
makes it send that EMCY (register 0x01, data 01 02).
"""

import logging
import sys

import canopen
from canopen import objectdictionary as od

logging.getLogger("can").setLevel(logging.ERROR)


def variable(name, index, data_type, access, default=None):
    v = od.ODVariable(name, index)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    return v


def main():
    host, port, node_id = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    dictionary = od.ObjectDictionary()
    dictionary.add_object(variable("Device name", 0x1008, od.VISIBLE_STRING, "ro", "python-canopen"))
    dictionary.add_object(variable("Producer heartbeat time", 0x1017, od.UNSIGNED16, "rw", 100))
    dictionary.add_object(variable("Blob", 0x2000, od.DOMAIN, "rw", b""))
    dictionary.add_object(variable("Counter", 0x2001, od.UNSIGNED32, "rw", 0))
    dictionary.add_object(variable("Offset", 0x2002, od.INTEGER16, "rw", 0))
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    node = canopen.LocalNode(node_id, dictionary)
    network.add_node(node)
    node.nmt.state = "PRE-OPERATIONAL"
    node.nmt.start_heartbeat(100)
    print("READY", flush=True)
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["emcy"]:
            node.emcy.send(int(words[1], 16), 0x01, b"\x01\x02")
    network.disconnect()


if __name__ == "__main__":
    main()
