"""Several actors in one driver process: one ``livecap run`` pipeline per actor, each in a thread.

``livecap run`` serves one actor per process. To measure how many actors ONE process sustains,
this builds each actor's pipeline exactly as ``livecap run`` does (its own argument parser and
``livecap.cli.run.build``: ZeroMQ source on ``markers.<actor>``, ZeroMQ sink on ``weights.<actor>``,
live defaults including ``--skip-stale``) and runs the pipelines in threads of this process, so
they share one interpreter (and its GIL) and one ZeroMQ context.

    python -m benchmarks.multi_driver --actors a0 a1 -- --zmq-in tcp://127.0.0.1:5555 --profile p.npz --mode qp

Prints ``ready: <weights address per actor, space separated>`` once every socket is bound; ends
when every pipeline has ended (``--idle-timeout`` passed to each). Each actor's stats go to
``<stats-dir>/<actor>.json``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--actors", nargs="+", required=True)
    ap.add_argument("--stats-dir", required=True)
    ap.add_argument("run_args", nargs=argparse.REMAINDER, help="-- then `livecap run` options shared by all actors")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from livecap.cli import build_parser
    from livecap.cli.run import build

    shared = [a for a in args.run_args if a != "--"]
    pipelines, outs = [], []
    for actor in args.actors:
        ns = build_parser().parse_args(["run", *shared, "--actor", actor, "--zmq-out", "tcp://127.0.0.1:0",
                                        "--stats-file", str(Path(args.stats_dir) / f"{actor}.json")])
        pipeline, described = build(ns)
        pipelines.append(pipeline)
        outs.append(next(d.split(" ", 1)[1] for d in described if d.startswith("zmq-out ")))
    threads = [threading.Thread(target=p.run, name=f"pipeline-{a}", daemon=True)
               for p, a in zip(pipelines, args.actors, strict=True)]
    print("ready: " + " ".join(outs), flush=True)
    for t in threads:
        t.start()
    try:
        for t in threads:
            t.join()
    except KeyboardInterrupt:
        for p in pipelines:
            p.stop()
        for t in threads:
            t.join(5)
    return 0


if __name__ == "__main__":
    sys.exit(main())
