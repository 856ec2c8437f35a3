"""A worker for the engine's protocol tests (runtime/src/worker.rs): Python's standard library
only. It echoes each request's first input path back as an output, and misbehaves on request:
an input path of `hang` never replies (nor answers a cancel), `crash` exits, `garbage` writes a
line that is not JSON, `bad item` replies with an error, `sleep:S` sleeps S seconds first,
`slow:S` works S seconds but stops when the engine cancels it (replying `error`, "cancelled"),
`slow-late:S` does the same and then replies `ok` to the cancelled request as well (a late reply),
`close-stdout` closes its stdout and goes on running, `unknown-id` replies to a request that was
never sent, `twice` replies twice, `long-line:N` writes N bytes to stdout without a newline (and
waits), `long-stderr:N` writes N bytes to stderr without a newline and then crashes.
`--die-at-start` exits before its hello; `--close-stdout-at-start` closes its stdout instead of
saying hello and goes on running; `--no-read` never reads stdin after its hello; `--every MODE`
takes every request as if its input path were MODE; `--op NAME` serves op NAME instead of `echo`;
`--pid-file PATH` starts a `sleep` in its process group and appends both pids to PATH (so that a
test can check that nothing of the worker outlives what ended it), and the id of each request it
gets to PATH.requests; `--protocol N` says it speaks protocol N; `--max-batch N` takes batches of
up to N requests (each answered on its own line, as a batched model would after one forward
pass); `--no-pong` ignores pings (a wedged worker).
"""
import json
import os
import select
import subprocess
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
    value = lambda flag, default: args[args.index(flag) + 1] if flag in args else default
    protocol = int(value("--protocol", 1))
    max_batch = int(value("--max-batch", 1))
    if "--pid-file" in args:
        child = subprocess.Popen(["sleep", "3600"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
        with open(value("--pid-file", None), "a") as f:
            f.write(f"{os.getpid()} {child.pid}\n")
    if "--close-stdout-at-start" in args:
        close_stdout_and_wait()
    send({"type": "hello", "protocol": protocol, "name": "protocol-test", "version": "1",
          "weights_digest": "", "ops": [value("--op", "echo")], "max_batch": max_batch})
    if "--no-read" in args:
        time.sleep(3600)
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


def close_stdout_and_wait():
    """Closes stdout (the engine reads its end) and lives on: a worker that is dead to the engine
    without exiting."""
    sys.stdout.flush()
    os.close(1)
    time.sleep(3600)


def answer(msg, lines):
    what = msg["inputs"][0]["path"] if msg.get("inputs") else ""
    if "--every" in sys.argv:
        what = sys.argv[sys.argv.index("--every") + 1]
    if "--pid-file" in sys.argv:
        with open(sys.argv[sys.argv.index("--pid-file") + 1] + ".requests", "a") as f:
            f.write(f"{msg['id']}\n")
    if what.startswith("sleep:"):
        time.sleep(float(what[6:]))
    if what.startswith("slow:") or what.startswith("slow-late:"):
        until = time.time() + float(what.split(":")[1])
        while time.time() < until:
            if lines.cancelled(msg["id"]):
                send({"type": "reply", "id": msg["id"], "status": "error", "message": "cancelled"})
                if what.startswith("slow-late:"):
                    send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": []})
                return
            time.sleep(0.01)
    if what == "close-stdout":
        close_stdout_and_wait()
    if what == "twice":
        send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": []})
    if what == "unknown-id":
        send({"type": "reply", "id": msg["id"] + 1000, "status": "ok", "outputs": []})
        return
    if what.startswith("long-line:"):
        n = int(what.split(":")[1])
        for _ in range(n // (1 << 20)):
            sys.stdout.write("x" * (1 << 20))
        sys.stdout.write("x" * (n % (1 << 20)))
        sys.stdout.flush()
        time.sleep(3600)
    if what.startswith("long-stderr:"):
        n = int(what.split(":")[1])
        for _ in range(n // (1 << 20)):
            sys.stderr.write("y" * (1 << 20))
        sys.stderr.write("y" * (n % (1 << 20)) + "\nasked to crash after a long line\n")
        sys.stderr.flush()
        sys.exit(1)
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
