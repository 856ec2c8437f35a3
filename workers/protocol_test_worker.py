"""A worker for the engine's protocol tests (runtime/src/worker.rs): Python's standard library
only. It echoes each request's first input path back as an output, and misbehaves on request:
an input path of `hang` never replies, `crash` exits, `garbage` writes a line that is not JSON,
`bad item` replies with an error, `sleep:S` sleeps S seconds first. `--die-at-start` exits
before its hello; `--protocol N` says it speaks protocol N; `--max-batch N` takes batches of up to
N requests (each answered on its own line, as a batched model would after one forward pass);
`--no-pong` ignores pings (a wedged worker).
"""
import json
import sys
import time


def send(msg):
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


def main():
    args = sys.argv[1:]
    if "--die-at-start" in args:
        print("no model here: exiting before the hello", file=sys.stderr, flush=True)
        sys.exit(3)
    protocol = int(args[args.index("--protocol") + 1]) if "--protocol" in args else 1
    max_batch = int(args[args.index("--max-batch") + 1]) if "--max-batch" in args else 1
    send({"type": "hello", "protocol": protocol, "name": "protocol-test", "version": "1",
          "weights_digest": "", "ops": ["echo"], "max_batch": max_batch})
    for line in sys.stdin:
        msg = json.loads(line)
        kind = msg.get("type")
        if kind == "shutdown":
            return
        if kind == "ping" and "--no-pong" not in args:
            send({"type": "pong", "id": msg["id"]})
            continue
        if kind == "request":
            answer(msg)
        if kind == "batch":
            assert len(msg["requests"]) <= max_batch, "a batch larger than the hello's max_batch"
            for request in msg["requests"]:
                answer(request)


def answer(msg):
    what = msg["inputs"][0]["path"] if msg.get("inputs") else ""
    if what.startswith("sleep:"):
        time.sleep(float(what[6:]))
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
