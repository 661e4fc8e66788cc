"""python-canopen's SDO client against a node, for `canlift bench sdo` (same server, same run).

usage: bench_sdo_python.py HOST PORT CHANNEL NODE READS SIZE
Prints one JSON object: expedited reads/s and segmented/block upload and download KiB/s.
"""

import json
import logging
import sys
import time

import canopen

logging.getLogger("can").setLevel(logging.ERROR)


def main():
    host, port, channel = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    node_id, reads, size = int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel=channel, tcp_tune=True)
    node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 5.0
    data = bytes(i & 0xFF for i in range(size))
    result = {}

    start = time.perf_counter()
    for _ in range(reads):
        node.sdo.upload(0x1000, 0)
    result["expedited_reads_per_s"] = reads / (time.perf_counter() - start)

    start = time.perf_counter()
    node.sdo.download(0x2000, 0, data)
    result["segmented_download_kib_s"] = size / 1024 / (time.perf_counter() - start)
    start = time.perf_counter()
    node.sdo.upload(0x2000, 0)
    result["segmented_upload_kib_s"] = size / 1024 / (time.perf_counter() - start)

    start = time.perf_counter()
    with node.sdo.open(0x2000, 0, "wb", size=size, block_transfer=True) as f:
        f.write(data)
    result["block_download_kib_s"] = size / 1024 / (time.perf_counter() - start)
    start = time.perf_counter()
    with node.sdo.open(0x2000, 0, "rb", block_transfer=True) as f:
        got = f.read()
    result["block_upload_kib_s"] = size / 1024 / (time.perf_counter() - start)
    assert got == data
    network.disconnect()
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
