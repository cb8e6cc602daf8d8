#!/usr/bin/env python3
"""Print asgreg's pose results as they arrive, from any host that reaches the zenoh router.

asgreg publishes every frame's result as JSON on ``asgreg/v3/<pipeline>/results/json``
(src/transport/keys.rs; fields: src/msg/json.rs). This script joins the ground station's router as
a zenoh client with scouting off (no multicast, no gossip) and prints one line per result.

    pip install eclipse-zenoh==1.10.2
    python3 examples/subscribe.py --connect tcp/192.168.10.1:7447 --pipeline default
    python3 examples/subscribe.py --count 10     # exit after 10 results
"""

import argparse
import json
import queue
import sys

import zenoh


def describe(result):
    """One line for one PoseResult."""
    name = result.get("name", "?")
    confidence = result.get("confidence")
    confidence = "?" if confidence is None else f"{confidence:.3f}"
    if result.get("accepted"):
        pose = result.get("cam_from_world") or {}
        q = pose.get("qvec_wxyz")
        t = pose.get("tvec_m")
        pose_text = f"q_wxyz={q} t_m={t}" if q and t else "no pose"
        return f"{name}: accepted confidence={confidence} {pose_text}"
    return f"{name}: rejected confidence={confidence} ({result.get('failure') or 'no reason given'})"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447",
                        help="the zenoh router's endpoint (default: %(default)s)")
    parser.add_argument("--pipeline", default="default",
                        help="the pipeline name (transport.pipeline; default: %(default)s)")
    parser.add_argument("--count", type=int, default=0,
                        help="exit after this many results (default: run until Ctrl-C)")
    args = parser.parse_args()

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")

    key = f"asgreg/v3/{args.pipeline}/results/json"
    try:
        session = zenoh.open(config)
    except Exception as error:  # zenoh raises ZError
        sys.exit(f"cannot connect to the zenoh router at {args.connect}: {error}")
    received = 0
    with session:
        # A bounded FIFO: the publisher blocks rather than drops if we fall behind.
        subscriber = session.declare_subscriber(key, zenoh.handlers.FifoChannel(64))
        print(f"subscribed to {key} via {args.connect}", file=sys.stderr, flush=True)
        try:
            while args.count <= 0 or received < args.count:
                sample = subscriber.recv()
                text = sample.payload.to_string()
                try:
                    result = json.loads(text)
                except json.JSONDecodeError as error:
                    print(f"not JSON on {sample.key_expr}: {error}", file=sys.stderr, flush=True)
                    continue
                print(describe(result), flush=True)
                received += 1
        except KeyboardInterrupt:
            pass
        subscriber.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
