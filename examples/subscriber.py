"""Minimal livecap weights subscriber (pyzmq + msgpack only; see docs/protocol.md).

    python examples/subscriber.py tcp://127.0.0.1:5556 --actor actor

Prints one line per frame: frame number, timestamp and the three strongest shapes.
"""

import argparse

import msgpack
import numpy as np
import zmq

parser = argparse.ArgumentParser()
parser.add_argument("address", help="where livecap run --zmq-out publishes, e.g. tcp://127.0.0.1:5556")
parser.add_argument("--actor", default="actor")
args = parser.parse_args()

sock = zmq.Context.instance().socket(zmq.SUB)
sock.connect(args.address)
sock.setsockopt(zmq.SUBSCRIBE, f"weights.{args.actor}".encode())

names = {}  # names_id -> shape names, learnt from header messages
while True:
    topic, payload = sock.recv_multipart()
    msg = msgpack.unpackb(payload)
    if msg["v"] != 1:
        continue  # a wire version this example does not know
    if msg["type"] == "header":
        names[msg["names_id"]] = msg["names"]
    elif msg["type"] == "weights" and msg["names_id"] in names:
        w = np.frombuffer(msg["weights"], dtype="<f4")
        top = np.argsort(-w)[:3]
        shapes = ", ".join(f"{names[msg['names_id']][i]} {w[i]:.2f}" for i in top)
        print(f"frame {msg['frame']:6d}  t {msg['timestamp']:8.3f}  {shapes}", flush=True)
