"""A fake gateway (NXg api 1, with canlift's bus events) in Python `websockets` (an independent WebSocket and TLS stack) that
pushes bus events as told and reports the subscriptions the portal registers
(crates/cloud/tests/python_events.rs, crates/cloud/tests/python_subscriptions.rs).

usage: event_gateway.py URL CA_FILE SERNUM
Connects (api 1), answers the portal's requests (every request succeeds with {"done": 0}; the
cloud token is kept for reconnections) and reads commands from standard input:
  EVENT {json}   push the event as a canopen_event notification
  CLOSE          close the connection
  CONNECT        connect again (with the token)
  QUIT           close and end
It prints "CONNACK API", "EVENTS [kinds]" when the portal registers events, "REG INHIBIT
THRESHOLD MPLEX,…" and "UNREG MPLEX,…" when it registers or unregisters objects, "CLOSED".
"""

import asyncio
import json
import ssl
import sys

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

URL, CA, SERNUM = sys.argv[1], sys.argv[2], sys.argv[3]
SSL = ssl.create_default_context(cafile=CA)


def say(*words):
    print(*words, flush=True)


class Gateway:
    def __init__(self):
        self.token = None
        self.ws = None
        self.reader = None

    async def connect(self):
        self.ws = await connect(URL, ssl=SSL, subprotocols=["cloud", "lift"])
        identity = {"sernum": SERNUM, "vendorid": 1050, "productcode": 4096, "liftnum": "py",
                    "hardware": "python", "software": "1", "api": 1, "boardhash": "00"}
        if self.token is not None:
            identity["cloudtoken"] = self.token
        await self.ws.send(json.dumps({"jsonrpc": "2.0", "method": "CONNECT", "id": 1,
                                       "params": {"identity": identity, "domaintoken": "MAS"}}))
        connack = json.loads(await self.ws.recv())
        say("CONNACK", connack.get("api"))
        self.reader = asyncio.create_task(self.serve(self.ws))

    async def serve(self, ws):
        try:
            async for text in ws:
                message = json.loads(text)
                method = message.get("method")
                if method == "update_unique_token":
                    self.token = message["params"]["token"]
                elif method == "reg_canopen_event":
                    say("EVENTS", json.dumps(message["params"]["events"]))
                elif method == "reg_canopen_object":
                    params = message["params"]
                    say("REG", params.get("inhibit", 0), float(params.get("threshold", 0)),
                        ",".join(params["mplex"]))
                elif method == "unreg_canopen_object":
                    say("UNREG", ",".join(message["params"]["mplex"]))
                if "id" in message and method is not None:
                    await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"],
                                              "result": {"done": 0}}))
        except ConnectionClosed:
            pass

    async def close(self):
        if self.ws is not None:
            await self.ws.close()
            await self.reader
            self.ws = None
            say("CLOSED")


async def main():
    gateway = Gateway()
    await gateway.connect()
    loop = asyncio.get_running_loop()
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if not line or line.strip() == "QUIT":
            await gateway.close()
            return
        command, _, rest = line.strip().partition(" ")
        if command == "EVENT":
            event = json.loads(rest)
            await gateway.ws.send(json.dumps({"jsonrpc": "2.0", "method": "canopen_event",
                                              "result": {"event": event}}))
        elif command == "CLOSE":
            await gateway.close()
        elif command == "CONNECT":
            await gateway.connect()


asyncio.run(main())
