"""A worker for the engine's protocol tests (runtime/src/worker.rs): Python's standard library
only. It echoes each request's first input path back as an output, and misbehaves on request:
an input path of `hang` never replies (nor answers a cancel), `crash` exits, `garbage` writes a
line that is not JSON, `bad item` replies with an error, `sleep:S` sleeps S seconds first, and
`slow:S` works S seconds but stops when the engine cancels it (replying `error`, "cancelled").
`--die-at-start` exits before its hello; `--protocol N` says it speaks protocol N; `--max-batch N`
takes batches of up to N requests (each answered on its own line, as a batched model would after
one forward pass); `--no-pong` ignores pings (a wedged worker).
"""
import json
import os
import select
import sys
import time


def send(msg):
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


class Lines:
    """Lines from stdin, read from the file descriptor so that a request at work can look for a
    cancel without blocking; messages seen meanwhile wait in `pending`."""

    def __init__(self):
        self.buf = b""
        self.pending = []

    def _fill(self, timeout):
        ready, _, _ = select.select([0], [], [], timeout)
        if not ready:
            return True
        chunk = os.read(0, 65536)
        self.buf += chunk
        return bool(chunk)

    def _take(self):
        line, self.buf = self.buf.split(b"\n", 1)
        return json.loads(line) if line.strip() else None

    def next(self):
        if self.pending:
            return self.pending.pop(0)
        while True:
            while b"\n" in self.buf:
                msg = self._take()
                if msg is not None:
                    return msg
            if not self._fill(None):
                return None

    def cancelled(self, request_id):
        """Whether a cancel for `request_id` has arrived (other messages are kept for later)."""
        self._fill(0)
        while b"\n" in self.buf:
            msg = self._take()
            if msg is None:
                continue
            if msg.get("type") == "cancel" and msg.get("id") == request_id:
                return True
            self.pending.append(msg)
        return False


def main():
    args = sys.argv[1:]
    if "--die-at-start" in args:
        print("no model here: exiting before the hello", file=sys.stderr, flush=True)
        sys.exit(3)
    protocol = int(args[args.index("--protocol") + 1]) if "--protocol" in args else 1
    max_batch = int(args[args.index("--max-batch") + 1]) if "--max-batch" in args else 1
    send({"type": "hello", "protocol": protocol, "name": "protocol-test", "version": "1",
          "weights_digest": "", "ops": ["echo"], "max_batch": max_batch})
    lines = Lines()
    while True:
        msg = lines.next()
        if msg is None:
            return
        kind = msg.get("type")
        if kind == "shutdown":
            return
        if kind == "ping" and "--no-pong" not in args:
            send({"type": "pong", "id": msg["id"]})
        if kind == "request":
            answer(msg, lines)
        if kind == "batch":
            assert len(msg["requests"]) <= max_batch, "a batch larger than the hello's max_batch"
            for request in msg["requests"]:
                answer(request, lines)


def answer(msg, lines):
    what = msg["inputs"][0]["path"] if msg.get("inputs") else ""
    if what.startswith("sleep:"):
        time.sleep(float(what[6:]))
    if what.startswith("slow:"):
        until = time.time() + float(what[5:])
        while time.time() < until:
            if lines.cancelled(msg["id"]):
                send({"type": "reply", "id": msg["id"], "status": "error", "message": "cancelled"})
                return
            time.sleep(0.01)
    if what == "hang":
        time.sleep(3600)
    if what == "crash":
        print("asked to crash", file=sys.stderr, flush=True)
        sys.exit(1)
    if what == "garbage":
        sys.stdout.write("this is not json\n")
        sys.stdout.flush()
        return
    if what == "bad item":
        send({"type": "reply", "id": msg["id"], "status": "error", "message": f"cannot do `{what}`"})
        return
    send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": [{"name": "echo", "path": what}]})


if __name__ == "__main__":
    main()
