"""A webhook receiver with Python's http.server and hmac (independent of canlift's HTTP and
signature code) for crates/cloud/tests/python_events.rs.

usage: webhook_receiver.py PORT SECRET FAILURES
Listens on 127.0.0.1:PORT; answers the first FAILURES POSTs with 500, the others with 204.
Prints "READY", then for every POST "HOOK STATUS VALID BODY" (VALID: whether X-Canlift-Signature
is the HMAC-SHA256 of the body under SECRET).
"""

import hashlib
import hmac
import sys
from http.server import BaseHTTPRequestHandler, HTTPServer

PORT, SECRET, FAILURES = int(sys.argv[1]), sys.argv[2].encode(), int(sys.argv[3])
seen = 0


class Hook(BaseHTTPRequestHandler):
    def do_POST(self):
        global seen
        body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
        expected = "sha256=" + hmac.new(SECRET, body, hashlib.sha256).hexdigest()
        valid = hmac.compare_digest(expected, self.headers.get("X-Canlift-Signature", ""))
        seen += 1
        status = 500 if seen <= FAILURES else 204
        print("HOOK", status, "valid" if valid else "invalid", body.decode(), flush=True)
        self.send_response(status)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args):
        pass


server = HTTPServer(("127.0.0.1", PORT), Hook)
print("READY", flush=True)
server.serve_forever()
