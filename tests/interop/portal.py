"""A portal written with Python `websockets` over Python's ssl (an independent WebSocket and TLS
stack), talking to a canlift gateway (crates/gateway/tests/python_portal.rs).

usage: portal.py CERT KEY
Prints `PORT n` once listening, then one `ANSWER name json` line per answer and `DONE`.
"""

import asyncio
import json
import ssl
import sys

from websockets.asyncio.server import serve

SERNUM = "180917010200000102"

SAMPLES = [
    ("heartbeat", {"jsonrpc": "2.0", "id": "<ID>", "method": "get_heartbeat"}),
    ("trip", {"jsonrpc": "2.0", "id": "<ID>", "method": "get_canopen_object",
              "params": {"lang": {"preferred_language": "de", "alternate_language": "en"},
                         "object": {"mplex": "0x652001", "compact": False, "stripped": False, "naked": False}}}),
    ("compact", {"jsonrpc": "2.0", "id": 7, "method": "get_canopen_object",
                 "params": {"object": {"mplex": "0x401001", "compact": True}}}),
    ("register", {"jsonrpc": "2.0", "method": "reg_canopen_object", "id": "<ID>",
                  "params": {"mplex": ["0x652001", "0x652002"], "inhibit": 1000, "threshold": 1}}),
    ("put", {"jsonrpc": "2.0", "method": "put_canopen_object", "id": "<ID>",
             "params": {"sernum": SERNUM, "object": {"mplex": "0x502200", "datatype": 7, "physunit": 0, "value": "2"}}}),
    ("readonly", {"jsonrpc": "2.0", "method": "put_canopen_object", "id": "<ID>",
                  "params": {"sernum": SERNUM, "object": {"mplex": "0x652001", "datatype": 7, "physunit": 26, "value": "9"}}}),
]


async def conversation(ws):
    print("SUBPROTOCOL", ws.subprotocol, flush=True)
    print("ORIGIN", ws.request.headers.get("Origin"), flush=True)
    connect = json.loads(await ws.recv())
    print("CONNECT", json.dumps(connect), flush=True)
    await ws.send(json.dumps({"jsonrpc": "2.0", "id": connect["id"], "result": "CONNACK", "api": 1}))
    notes = []
    for name, request in SAMPLES:
        await ws.send(json.dumps(request))
        while True:
            message = json.loads(await ws.recv())
            if "method" in message:
                notes.append(message)
                continue
            print("ANSWER", name, json.dumps(message), flush=True)
            break
    # The car travels to floor 2: the trip counter is pushed.
    while not any(n["result"] == {"mplex": "0x652001", "value": "1"} for n in notes):
        notes.append(json.loads(await asyncio.wait_for(ws.recv(), 20)))
    for n in notes:
        print("NOTE", json.dumps(n), flush=True)
    print("DONE", flush=True)
    await ws.close()
    stop.set_result(None)


async def main():
    global stop
    stop = asyncio.get_running_loop().create_future()
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(sys.argv[1], sys.argv[2])
    async with serve(conversation, "127.0.0.1", 0, ssl=context, subprotocols=["cloud", "lift"]) as server:
        port = server.sockets[0].getsockname()[1]
        print("PORT", port, flush=True)
        await asyncio.wait_for(stop, 60)


if __name__ == "__main__":
    asyncio.run(main())
