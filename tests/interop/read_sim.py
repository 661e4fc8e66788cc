"""python-canopen reads the simulated lift through the hub using canlift's exported EDS
(crates/canlift/tests/sim_cli.rs).

usage: read_sim.py HOST PORT CHANNEL EDS NODE
Calls the car to floor 3 through 0x5022 and prints one line per fact, `key value`.
"""

import sys
import time

import canopen


def main():
    host, port, channel, eds, node_id = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], int(sys.argv[5])
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel=channel)
    try:
        node = network.add_node(node_id, eds)
        print("device_type", hex(node.sdo[0x1000].raw), flush=True)
        # Names come from the EDS canlift exported (the catalog's English names).
        counters = node.sdo["Lift counters"]
        print("trip_name", counters[1].od.name, flush=True)
        print("trips_before", counters["Trip counter [trips]"].raw, flush=True)
        floors = node.sdo["Floor level positions"]
        print("floors", ",".join(str(floors[i].raw) for i in range(1, floors[0].raw + 1)), flush=True)
        print("lantern", node.sdo[0x4112].raw, flush=True)
        node.sdo["Passenger call"].raw = 3
        deadline = time.monotonic() + 30
        while counters[1].raw < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        print("trips_after", counters[1].raw, flush=True)
        print("position", node.sdo["Position value"][1].raw, flush=True)
        try:
            node.sdo["Passenger call"].raw = 9
            print("abort none", flush=True)
        except canopen.SdoAbortedError as e:
            print("abort", hex(e.code), flush=True)
    finally:
        network.disconnect()


if __name__ == "__main__":
    main()
