#!/usr/bin/env python3
"""Print asgreg's pose results, change results and fused change sets as they arrive, from any host that reaches the zenoh router.

asgreg publishes every frame's result as JSON on ``asgreg/v9/<pipeline>/results/json``, and,
when the pipeline runs change detection (``workers.change`` > 0), every frame's change result on
``asgreg/v9/<pipeline>/changes/json`` and the fused change set on
``asgreg/v9/<pipeline>/changeset/json`` (now and then, and once with ``complete: true``)
(src/transport/keys.rs; fields: src/msg/json.rs, schemas/v9/*.schema.json). This script joins
the ground station's router as a zenoh client with scouting off (no multicast, no gossip) and
prints one line per message; with --changes-out it also writes the final change set as GeoJSON.

    pip install eclipse-zenoh==1.10.2
    python3 examples/subscribe.py --connect tcp/192.168.10.1:7447 --pipeline default
    python3 examples/subscribe.py --count 10     # exit after 10 pose results
    python3 examples/subscribe.py --until-change-set --changes-out changes.geojson
"""

import argparse
import json
import queue
import sys
import time

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


def describe_change(result):
    """One line for one ChangeResult."""
    name = result.get("name", "?")
    if result.get("failure"):
        return f"{name}: no change map ({result['failure']})"
    regions = result.get("regions") or []
    parts = [
        f"{r['kind']} {r['footprint_area_m2']:.0f} m2 {r['height_m']:.1f} m high at "
        f"({r['centroid_m'][0]:.1f}, {r['centroid_m'][1]:.1f})"
        for r in regions
    ]
    return f"{name}: {len(regions)} change regions in {result.get('change_ms', 0):.1f} ms" + (
        ": " + "; ".join(parts) if parts else "")


def describe_change_set(change_set):
    """Lines for one ChangeSet."""
    objects = change_set.get("objects") or []
    confirmed = sum(1 for o in objects if o.get("confirmed"))
    state = "final" if change_set.get("complete") else "so far"
    lines = [f"change set ({state}): {len(objects)} objects, {confirmed} confirmed, "
             f"from {change_set.get('frames_with_map')} change maps of "
             f"{change_set.get('frames_with_result')} frames"]
    free_space = free_space_by_object(change_set)
    for index, o in enumerate(objects):
        line = (f"  {o['kind']:<7} {o['footprint_area_m2']:7.1f} m2 {o['height_m']:5.1f} m high "
                f"frames {o['frames']} {'confirmed' if o.get('confirmed') else 'unconfirmed'}")
        check = free_space.get(index)
        if check is not None:
            line += (f" (free space: seen through by frames {check['seen_through_by']}, "
                     f"agreed by {check['agreed_by']}{', refuted' if check.get('refuted') else ''})")
        lines.append(line)
    return "\n".join(lines)


def free_space_by_object(change_set):
    """The free-space test of each tested object (confirmed `added` ones), by object index."""
    return {check["object"]: check for check in change_set.get("free_space") or []}


# Seconds a subscriber that stops at the final change set keeps listening for change results
# still on their way (another key than the set's, so not ordered with it).
CHANGE_RESULTS_GRACE_S = 2.0


def change_set_geojson(change_set):
    """The fused objects as a GeoJSON FeatureCollection (coordinates: the model's frame)."""
    features = []
    free_space = free_space_by_object(change_set)
    for index, o in enumerate(change_set.get("objects") or []):
        ring = [list(p) for p in o.get("footprint_m") or []]
        if ring:
            ring.append(ring[0])
        properties = {k: v for k, v in o.items() if k != "footprint_m"}
        check = free_space.get(index)
        if check is not None:
            properties["seen_through_by"] = check["seen_through_by"]
            properties["agreed_by"] = check["agreed_by"]
            properties["refuted"] = check["refuted"]
        features.append({"type": "Feature", "id": index,
                         "geometry": {"type": "Polygon", "coordinates": [ring]},
                         "properties": properties})
    return {"type": "FeatureCollection", "features": features}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447",
                        help="the zenoh router's endpoint (default: %(default)s)")
    parser.add_argument("--pipeline", default="default",
                        help="the pipeline name (transport.pipeline; default: %(default)s)")
    parser.add_argument("--count", type=int, default=0,
                        help="exit after this many pose results (default: run until Ctrl-C)")
    parser.add_argument("--until-change-set", action="store_true",
                        help="exit once the final (complete) change set has arrived")
    parser.add_argument("--changes-out", default=None,
                        help="write the final change set here as GeoJSON")
    args = parser.parse_args()

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")

    prefix = f"asgreg/v9/{args.pipeline}"
    keys = {f"{prefix}/results/json": "pose", f"{prefix}/changes/json": "change",
            f"{prefix}/changeset/json": "change_set"}
    try:
        session = zenoh.open(config)
    except Exception as error:  # zenoh raises ZError
        sys.exit(f"cannot connect to the zenoh router at {args.connect}: {error}")
    received = 0
    seen = set()
    final_set = None
    # One queue for the three subscriptions, so messages print in arrival order.
    arrived = queue.Queue(maxsize=256)
    with session:
        subscribers = [
            session.declare_subscriber(key, lambda sample, kind=kind: arrived.put((kind, sample)))
            for key, kind in keys.items()
        ]
        print(f"subscribed to {', '.join(keys)} via {args.connect}", file=sys.stderr, flush=True)
        try:
            # With --count and/or --until-change-set: exit once all the asked-for have arrived.
            while not ((args.count > 0 or args.until_change_set)
                       and (args.count <= 0 or received >= args.count)
                       and (not args.until_change_set or final_set is not None)):
                kind, sample = arrived.get()
                text = sample.payload.to_string()
                try:
                    message = json.loads(text)
                except json.JSONDecodeError as error:
                    print(f"not JSON on {sample.key_expr}: {error}", file=sys.stderr, flush=True)
                    continue
                # The station sends a result again until its collector acknowledges it: keep
                # the first per frame id (a repeat is a re-delivery of the same result).
                if kind in ("pose", "change"):
                    frame_id = message.get("frame_id")
                    if (kind, frame_id) in seen:
                        continue
                    seen.add((kind, frame_id))
                if kind == "pose":
                    print(describe(message), flush=True)
                    received += 1
                elif kind == "change":
                    print(describe_change(message), flush=True)
                else:
                    print(describe_change_set(message), flush=True)
                    if message.get("complete") and final_set is None:
                        final_set = message
            # The change results and the change set travel on different keys, which zenoh does
            # not order with each other: a frame's change result may arrive after the final set.
            # Keep listening until the set's frames have theirs, or for a grace period.
            if final_set is not None:
                expected = final_set.get("frames_with_result") or 0
                grace_ends = time.monotonic() + CHANGE_RESULTS_GRACE_S
                while sum(1 for kind, _ in seen if kind == "change") < expected:
                    left = grace_ends - time.monotonic()
                    if left <= 0:
                        break
                    try:
                        kind, sample = arrived.get(timeout=left)
                    except queue.Empty:
                        break
                    if kind != "change":
                        continue
                    try:
                        message = json.loads(sample.payload.to_string())
                    except json.JSONDecodeError:
                        continue
                    if (kind, message.get("frame_id")) not in seen:
                        seen.add((kind, message.get("frame_id")))
                        print(describe_change(message), flush=True)
        except KeyboardInterrupt:
            pass
        for subscriber in subscribers:
            subscriber.undeclare()
    if final_set is not None and args.changes_out:
        with open(args.changes_out, "w", encoding="utf-8") as out:
            json.dump(change_set_geojson(final_set), out, indent=1)
        print(f"wrote {args.changes_out}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
