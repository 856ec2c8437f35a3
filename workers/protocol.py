"""The worker side of dist4d's protocol (docs/workers.md), standard library only: say hello,
then answer requests with `handle(op, files, params, out_dir, item) -> {output name: path}` until
`shutdown`. An exception in `handle` fails that item (status `error`, its repr as the message,
logged on stderr); the worker goes on.

A worker whose hello says `max_batch` > 1 also gets `batch` messages (several requests at once);
`serve` answers them one by one through `handle` unless it is given `handle_batch(requests) ->
[outputs or exception]`, where a model runs them as one tensor batch (with `handle=None`, single
requests go to `handle_batch` too).
"""
import json
import sys


def send(msg):
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


def reply(msg, outputs):
    if isinstance(outputs, Exception):  # the item fails, the worker goes on
        print(f"request {msg.get('id')} ({msg.get('item', '')}): {outputs!r}", file=sys.stderr, flush=True)
        send({"type": "reply", "id": msg["id"], "status": "error", "message": repr(outputs)})
    else:
        send({"type": "reply", "id": msg["id"], "status": "ok",
              "outputs": [{"name": k, "path": str(v)} for k, v in outputs.items()]})


def one(handle, msg):
    try:
        files = {f["name"]: f["path"] for f in msg["inputs"]}
        return handle(msg["op"], files, msg.get("params", {}), msg["out_dir"], msg.get("item", ""))
    except Exception as e:
        return e


def batch(handle_batch, requests):
    try:
        return handle_batch(requests)
    except Exception as e:  # the whole batch fails, the worker goes on
        return [e] * len(requests)


def serve(hello, handle, handle_batch=None):
    send({"type": "hello", "protocol": 1, "weights_digest": "", "max_batch": 1, **hello})
    for line in sys.stdin:
        msg = json.loads(line)
        kind = msg.get("type")
        if kind == "shutdown":
            return
        if kind == "ping":
            send({"type": "pong", "id": msg["id"]})
        elif kind == "request":
            reply(msg, one(handle, msg) if handle is not None else batch(handle_batch, [msg])[0])
        elif kind == "batch":
            requests = msg["requests"]
            if handle_batch is not None:
                results = batch(handle_batch, requests)
            else:
                results = [one(handle, r) for r in requests]
            for r, outputs in zip(requests, results):
                reply(r, outputs)
