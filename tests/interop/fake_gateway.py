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


EVENTS_REFUSED = []


async def next_request(ws, timeout=10):
    """The portal's next message but `reg_canopen_event`, which this gateway (NXg SW003 v1.0.0
    without canlift's extension) does not have: answered -32601 like any unknown method."""
    while True:
        message = json.loads(await asyncio.wait_for(ws.recv(), timeout))
        if message.get("method") != "reg_canopen_event":
            return message
        EVENTS_REFUSED.append(message["params"]["events"])
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"],
                                  "error": {"code": -32601, "message": "Method not found"}}))


async def closed_without_answer(ws):
    try:
        message = await next_request(ws)
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
        update = await next_request(ws)
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
        report("known", (await next_request(first))["result"])
        async with connect(URL, ssl=SSL, subprotocols=["lift"]) as second:
            await second.send(connect_message(token))
            report("second", (await next_request(second))["result"])
            report("first_after_second", await closed_without_answer(first))
            # The portal's heartbeat reaches the connection in service, events refused or not.
            report("heartbeat", (await next_request(second))["method"])
            report("events_refused", EVENTS_REFUSED)
    # NXg §5.3: WebSocket pings prove nothing (a proxy may answer them for a gateway that is
    # gone). A gateway that pings every 0.5 s and answers the portal's pings, yet leaves its
    # get_heartbeat requests unanswered, is dropped after 2 × heartbeat + 30 s (32 s here).
    async with connect(URL, ssl=SSL, subprotocols=["cloud"], ping_interval=0.5) as ws:
        await ws.send(connect_message(token))
        json.loads(await ws.recv())
        started = asyncio.get_running_loop().time()
        heartbeats = 0
        try:
            while True:
                message = await next_request(ws, 45)
                heartbeats += message.get("method") == "get_heartbeat"
        except ConnectionClosed:
            report("pinging_unanswered", "closed")
        except asyncio.TimeoutError:
            report("pinging_unanswered", "open")
        report("pinging_lasted_s", round(asyncio.get_running_loop().time() - started))
        report("pinging_heartbeats", heartbeats)
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
