"""The worker side of dist4d's protocol (docs/workers.md), standard library only: say hello,
then answer requests with `handle(op, files, params, out_dir) -> {output name: path}` until
`shutdown`. An exception in `handle` fails that item (status `error`, its repr as the message,
logged on stderr); the worker goes on.
"""
import json
import sys


def send(msg):
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


def serve(hello, handle):
    send({"type": "hello", "protocol": 1, "weights_digest": "", "max_batch": 1, **hello})
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
        try:
            files = {f["name"]: f["path"] for f in msg["inputs"]}
            outputs = handle(msg["op"], files, msg.get("params", {}), msg["out_dir"])
            send({"type": "reply", "id": msg["id"], "status": "ok",
                  "outputs": [{"name": k, "path": str(v)} for k, v in outputs.items()]})
        except Exception as e:  # the item fails, the worker goes on
            print(f"request {msg.get('id')}: {e!r}", file=sys.stderr, flush=True)
            send({"type": "reply", "id": msg["id"], "status": "error", "message": repr(e)})
