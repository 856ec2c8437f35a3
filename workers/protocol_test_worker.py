"""A worker for the engine's protocol tests (runtime/src/worker.rs): Python's standard library
only. It echoes each request's first input path back as an output, and misbehaves on request:
an input path of `hang` never replies, `crash` exits, `garbage` writes a line that is not JSON,
`bad item` replies with an error. `--die-at-start` exits before its hello; `--protocol N` says
it speaks protocol N.
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
    send({"type": "hello", "protocol": protocol, "name": "protocol-test", "version": "1",
          "weights_digest": "", "ops": ["echo"], "max_batch": 1})
    for line in sys.stdin:
        msg = json.loads(line)
        kind = msg.get("type")
        if kind == "shutdown":
            return
        if kind == "ping":
            send({"type": "pong", "id": msg["id"]})
            continue
        if kind != "request":
            continue
        what = msg["inputs"][0]["path"] if msg.get("inputs") else ""
        if what == "hang":
            time.sleep(3600)
        if what == "crash":
            print("asked to crash", file=sys.stderr, flush=True)
            sys.exit(1)
        if what == "garbage":
            sys.stdout.write("this is not json\n")
            sys.stdout.flush()
            continue
        if what == "bad item":
            send({"type": "reply", "id": msg["id"], "status": "error", "message": f"cannot do `{what}`"})
            continue
        send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": [{"name": "echo", "path": what}]})


if __name__ == "__main__":
    main()
