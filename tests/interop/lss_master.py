"""python-canopen's LSS master against canlift LocalNodes without a node-ID
(crates/canopen/tests/python_nmt.rs).

usage: lss_master.py HOST PORT NODE_ID
Fastscan finds the unconfigured slave with the lowest LSS address; it gets NODE_ID, stores it
and is switched back to waiting. Prints FOUND with the address, then OK.
"""

import logging
import sys
import time

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, node_id = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    network.lss.RESPONSE_TIMEOUT = 0.05
    # The hub holds frames for 50 ms after a client enters raw mode (python-can reads the
    # handshake reply alone); the short Fastscan timeout must not fall into that window.
    time.sleep(0.2)
    print("READY", flush=True)
    found, address = network.lss.fast_scan()
    if not found:
        sys.exit("FAIL: fast scan found nobody")
    print("FOUND " + " ".join(f"{part:08X}" for part in address), flush=True)
    network.lss.RESPONSE_TIMEOUT = 0.5
    if network.lss.inquire_node_id() != 0xFF:
        sys.exit("FAIL: the slave should have no node-ID yet")
    network.lss.configure_node_id(node_id)
    network.lss.store_configuration()
    network.lss.send_switch_state_global(network.lss.WAITING_STATE)
    network.disconnect()
    print("OK", flush=True)


if __name__ == "__main__":
    main()
