"""A python-canopen LocalNode with one TPDO and one RPDO, for `canlift pdo show|set`
(crates/canlift/tests/tools_cli.rs).

usage: pdo_node.py HOST PORT NODE
Objects: 1400h/1600h (RPDO1), 1800h/1A00h (TPDO1, off, no mapping), 2001h UNSIGNED32 rw,
2002h INTEGER16 rw. Prints READY; on a line "check" on standard input it reads its own PDO
configuration the way python-canopen's PDO module does (decoding the mapping against its
dictionary) and prints it as JSON; on "send COUNTER OFFSET" it sets the two objects through
TPDO1's mapping and transmits TPDO1 once, then prints SENT; serves until standard input closes.
"""

import json
import logging
import sys

import canopen
from canopen import objectdictionary as od

logging.getLogger("can").setLevel(logging.ERROR)


def variable(name, index, sub, data_type, default):
    v = od.ODVariable(name, index, sub)
    v.data_type = data_type
    v.access_type = "rw"
    v.default = default
    return v


def record(name, index, subs):
    r = od.ODRecord(name, index)
    for sub, (sub_name, data_type, default) in subs.items():
        r.add_member(variable(sub_name, index, sub, data_type, default))
    return r


def mapping(name, index):
    subs = {0: ("Number of mapped objects", od.UNSIGNED8, 0)}
    for sub in range(1, 9):
        subs[sub] = (f"Mapped object {sub}", od.UNSIGNED32, 0)
    return record(name, index, subs)


def main():
    host, port, node_id = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    d = od.ObjectDictionary()
    d.add_object(record("RPDO1 communication", 0x1400, {
        0: ("Highest sub-index", od.UNSIGNED8, 5),
        1: ("COB-ID", od.UNSIGNED32, 0x200 + node_id),
        2: ("Transmission type", od.UNSIGNED8, 255),
        5: ("Event timer", od.UNSIGNED16, 0),
    }))
    d.add_object(mapping("RPDO1 mapping", 0x1600))
    d.add_object(record("TPDO1 communication", 0x1800, {
        0: ("Highest sub-index", od.UNSIGNED8, 5),
        1: ("COB-ID", od.UNSIGNED32, 0xC0000180 + node_id),
        2: ("Transmission type", od.UNSIGNED8, 255),
        3: ("Inhibit time", od.UNSIGNED16, 0),
        5: ("Event timer", od.UNSIGNED16, 0),
    }))
    d.add_object(mapping("TPDO1 mapping", 0x1A00))
    counter = od.ODVariable("Counter", 0x2001)
    counter.data_type, counter.access_type, counter.default = od.UNSIGNED32, "rw", 0
    offset = od.ODVariable("Offset", 0x2002)
    offset.data_type, offset.access_type, offset.default = od.INTEGER16, "rw", 0
    d.add_object(counter)
    d.add_object(offset)
    heartbeat = od.ODVariable("Producer heartbeat time", 0x1017)
    heartbeat.data_type, heartbeat.access_type, heartbeat.default = od.UNSIGNED16, "rw", 0
    d.add_object(heartbeat)
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    node = canopen.LocalNode(node_id, d)
    network.add_node(node)
    node.nmt.state = "PRE-OPERATIONAL"
    print("READY", flush=True)
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["send"]:
            tpdo = node.tpdo[1]
            tpdo.read(from_od=False)
            tpdo["Counter"].raw = int(words[1], 0)
            tpdo["Offset"].raw = int(words[2], 0)
            tpdo.transmit()
            print("SENT", flush=True)
        if line.strip() == "check":
            tpdo = node.tpdo[1]
            tpdo.read(from_od=False)
            print(json.dumps({
                "cob_id": tpdo.cob_id,
                "enabled": tpdo.enabled,
                "trans_type": tpdo.trans_type,
                "inhibit_time": tpdo.inhibit_time,
                "event_timer": tpdo.event_timer,
                "map": [[v.index, v.subindex, v.length] for v in tpdo.map],
            }), flush=True)
    network.disconnect()


if __name__ == "__main__":
    main()
