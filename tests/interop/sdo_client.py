"""python-canopen's SDO client against a canlift SDO server (crates/canopen/tests/python_canopen.rs).

usage: sdo_client.py HOST PORT NODE
The canlift node serves 0x1000 UNSIGNED32 ro = 0x000101A1 and 0x2002 DOMAIN rw. Every size is
written and read back with expedited/segmented transfers, then with block transfers.
"""

import logging
import sys

import canopen
from canopen.sdo.exceptions import SdoAbortedError

logging.getLogger("can").setLevel(logging.ERROR)

SIZES = [1, 2, 3, 4, 5, 6, 7, 8, 13, 14, 100, 889, 890, 4096, 65536]


def pattern(n):
    return bytes((i * 13 + n) & 0xFF for i in range(n))


def main():
    host, port, node_id = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0", tcp_tune=True)
    try:
        node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 2.0

        assert node.sdo.upload(0x1000, 0) == bytes.fromhex("A1010100"), "expedited read"
        try:
            node.sdo.download(0x1000, 0, b"\x00\x00\x00\x00")
            sys.exit("FAIL: write to a read-only object succeeded")
        except SdoAbortedError as e:
            assert e.code == 0x06010002, hex(e.code)
        try:
            node.sdo.upload(0x3000, 0)
            sys.exit("FAIL: read of a missing object succeeded")
        except SdoAbortedError as e:
            assert e.code == 0x06020000, hex(e.code)

        for n in SIZES:
            data = pattern(n)
            node.sdo.download(0x2002, 0, data)  # expedited up to 4 bytes, else segmented
            got = node.sdo.upload(0x2002, 0)
            assert got == data, f"segmented round trip of {n} bytes"
            node.sdo.download(0x2002, 0, data, force_segment=True)
            assert node.sdo.upload(0x2002, 0) == data, f"forced segmented {n}"

            block = pattern(n + 1)[:n]
            with node.sdo.open(0x2002, 0, "wb", size=n, block_transfer=True) as f:
                f.write(block)
            with node.sdo.open(0x2002, 0, "rb", block_transfer=True) as f:
                got = f.read()
            assert got == block, f"block round trip of {n} bytes: {len(got)} bytes back"
            print(f"size {n}: ok", flush=True)
    finally:
        network.disconnect()
    print("OK", flush=True)


if __name__ == "__main__":
    main()
