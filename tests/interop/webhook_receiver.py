"""A webhook receiver with Python's http.server (independent of canlift's HTTP code) for
crates/cloud/tests/integration/python_events.rs. Each delivery is checked with the Standard
Webhooks reference library (`standardwebhooks`, independent of canlift's signature code) and
with the verifier docs/PORTAL.md §Webhooks shows (VERIFIER: that code, extracted by the test),
which must also refuse the same delivery replayed five minutes and a second later.

usage: webhook_receiver.py PORT SECRET FAILURES VERIFIER
Listens on 127.0.0.1:PORT; answers the first FAILURES POSTs with 500, the others with 204.
Prints "READY", then for every POST "HOOK STATUS VALID REPLAY AUTH BODY": VALID is "valid" when
both checks pass, REPLAY "replay-refused" when the documented verifier refuses the replay, AUTH
the Basic credentials received ("-": none).
"""

import base64
import importlib.util
import sys
from http.server import BaseHTTPRequestHandler, HTTPServer

import standardwebhooks

PORT, SECRET, FAILURES, VERIFIER = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
spec = importlib.util.spec_from_file_location("documented", VERIFIER)
documented = importlib.util.module_from_spec(spec)
spec.loader.exec_module(documented)
seen = 0


class Hook(BaseHTTPRequestHandler):
    def do_POST(self):
        global seen
        body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
        headers = {k.lower(): v for k, v in self.headers.items()}
        try:
            standardwebhooks.Webhook(SECRET).verify(body, headers)
            documented.verify(SECRET, headers, body)
            valid = "valid"
        except Exception as e:  # noqa: BLE001 - any failure is an invalid delivery
            valid = "invalid:" + type(e).__name__
        try:
            later = int(headers.get("webhook-timestamp", "0")) + 301
            documented.verify(SECRET, headers, body, now=later)
            replay = "replay-accepted"
        except ValueError:
            replay = "replay-refused"
        auth = self.headers.get("Authorization", "")
        auth = base64.b64decode(auth[len("Basic "):]).decode() if auth.startswith("Basic ") else "-"
        seen += 1
        status = 500 if seen <= FAILURES else 204
        print("HOOK", status, valid, replay, auth, body.decode(), flush=True)
        self.send_response(status)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args):
        pass


server = HTTPServer(("127.0.0.1", PORT), Hook)
print("READY", flush=True)
server.serve_forever()
