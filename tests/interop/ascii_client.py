"""A CiA 309-3 ASCII client written from the command syntax CANopenNode's gateway documents
(CO_gateway_ascii.h), not from canlift's code: it checks canlift's `ascii` gateway.

usage: ascii_client.py HOST PORT
Reads one command per line on standard input (without a sequence number), sends each as
"[<n>] <command>\\r\\n" with n counting from 1, reads the reply: any number of lines, the last
one starting with "[<n>] ", ending in CR LF. Prints one JSON object per command:
{"command", "lines" (those before the last), "kind": "ok" | "value" | "error", "value",
"code" (int for gateway errors, "0x…" for SDO abort codes), "comment"}.
"""

import json
import re
import socket
import sys

LAST = re.compile(r"^\[(\d+)\] (.*)$")
ERROR = re.compile(r"^ERROR:\s*(0x[0-9A-Fa-f]{8}|\d+)\s*(?:#(.*))?$")


def read_line(stream):
    raw = stream.readline()
    if not raw:
        raise EOFError("gateway closed the connection")
    if not raw.endswith(b"\r\n"):
        raise ValueError(f"reply line without CR LF: {raw!r}")
    return raw[:-2].decode("utf-8")


def main():
    host, port = sys.argv[1], int(sys.argv[2])
    sock = socket.create_connection((host, port), timeout=60)
    stream = sock.makefile("rb")
    for n, command in enumerate((c.rstrip("\n") for c in sys.stdin), start=1):
        sock.sendall(f"[{n}] {command}\r\n".encode("utf-8"))
        lines = []
        while True:
            line = read_line(stream)
            m = LAST.match(line)
            if m and int(m.group(1)) == n:
                body = m.group(2)
                break
            lines.append(line)
        result = {"command": command, "lines": lines}
        e = ERROR.match(body)
        if body == "OK":
            result["kind"] = "ok"
        elif e:
            code = e.group(1)
            result.update(
                kind="error",
                code=code if code.startswith("0x") else int(code),
                comment=(e.group(2) or "").strip(),
            )
        else:
            result.update(kind="value", value=body)
        print(json.dumps(result), flush=True)
    sock.close()


if __name__ == "__main__":
    main()
