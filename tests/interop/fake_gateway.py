"""A fake gateway in Python `websockets` (an independent WebSocket and TLS stack) checks the
portal's identity and token rules (crates/cloud/tests/python_gateway.rs).

usage: fake_gateway.py URL CA_FILE
Prints one `name value` line per finding and `DONE`.
"""

import asyncio
import json
import ssl
import sys

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

URL, CA = sys.argv[1], sys.argv[2]
SSL = ssl.create_default_context(cafile=CA)
IDENTITY = {"sernum": "PY-0001", "vendorid": 1050, "productcode": 4096, "liftnum": "py", "hardware": "python",
            "software": "1", "api": 1, "boardhash": "00"}


def report(name, value):
    print(name, json.dumps(value), flush=True)


def connect_message(token=None):
    identity = dict(IDENTITY)
    if token is not None:
        identity["cloudtoken"] = token
    return json.dumps({"jsonrpc": "2.0", "method": "CONNECT", "id": 1,
                       "params": {"identity": identity, "domaintoken": "MAS"}})


async def closed_without_answer(ws):
    try:
        message = await asyncio.wait_for(ws.recv(), 10)
        return f"answered: {message}"
    except ConnectionClosed:
        return "closed"


async def main():
    # First contact: CONNACK, then the portal issues a token; we store it and confirm.
    async with connect(URL, ssl=SSL, subprotocols=["cloud", "lift"]) as ws:
        report("subprotocol", ws.subprotocol)
        await ws.send(connect_message())
        connack = json.loads(await ws.recv())
        report("connack", connack)
        update = json.loads(await ws.recv())
        report("update_method", update["method"])
        token = update["params"]["token"]
        report("token_sernum", update["params"]["sernum"])
        report("token_length", len(token))
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": update["id"], "result": {"done": 0}}))
        await asyncio.sleep(0.3)
    # A wrong token: closed without an answer.
    async with connect(URL, ssl=SSL, subprotocols=["cloud"]) as ws:
        await ws.send(connect_message("0" * 32))
        report("wrong_token", await closed_without_answer(ws))
    # No token although one was issued: refused too.
    async with connect(URL, ssl=SSL, subprotocols=["cloud"]) as ws:
        await ws.send(connect_message())
        report("missing_token", await closed_without_answer(ws))
    # The right token: accepted without a new token; a second valid connection replaces it.
    async with connect(URL, ssl=SSL, subprotocols=["lift"]) as first:
        await first.send(connect_message(token))
        report("known", json.loads(await first.recv())["result"])
        async with connect(URL, ssl=SSL, subprotocols=["lift"]) as second:
            await second.send(connect_message(token))
            report("second", json.loads(await second.recv())["result"])
            report("first_after_second", await closed_without_answer(first))
            # The portal's heartbeat reaches the connection in service.
            request = json.loads(await asyncio.wait_for(second.recv(), 10))
            report("heartbeat", request["method"])
    # No CONNECT within the timeout: closed.
    async with connect(URL, ssl=SSL, subprotocols=["cloud"]) as ws:
        report("silent", await closed_without_answer(ws))
    # Neither subprotocol offered: the upgrade is refused.
    try:
        async with connect(URL, ssl=SSL, subprotocols=["chat"]):
            report("no_subprotocol", "accepted")
    except InvalidStatus as e:
        report("no_subprotocol", e.response.status_code)
    print("DONE", flush=True)


if __name__ == "__main__":
    asyncio.run(main())
