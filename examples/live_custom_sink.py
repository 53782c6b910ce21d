"""A live session from Python with a sink of your own: a take replayed as the source, and a sink that
prints when the jaw opens past a threshold (livecap's API, docs/api.md).

    python examples/live_custom_sink.py recordings/demo_take.c3d --rig recordings/demo_rig.npz [--frames 600]

Any iterable of MarkerFrames is a source (a transport source, a generator); any object with
``publish(result)`` and ``close()`` is a sink.
"""

import sys

import livecap


class JawOpenEvents:
    """Prints the frames where jawOpen crosses ``threshold`` upwards; counts them."""

    def __init__(self, threshold: float = 0.5) -> None:
        self.threshold, self.open, self.events = threshold, False, 0

    def publish(self, result: livecap.SolveResult) -> None:
        now_open = result.weights[result.names.index("jawOpen")] > self.threshold
        if now_open and not self.open:
            self.events += 1
            print(f"frame {result.frame:5d} t={result.timestamp:6.2f} s: jaw opens")
        self.open = now_open

    def close(self) -> None:
        print(f"{self.events} jaw openings")


def main(argv: list[str]) -> int:
    take_path, rest = argv[0], argv[1:]
    opts = dict(zip(rest[::2], rest[1::2], strict=True))
    rig = livecap.load_rig(opts["--rig"])
    layout = livecap.load_layout(opts["--rig"], rig)
    take = livecap.load_take(take_path)
    profile = livecap.calibrate(take.slice(0, int(take.rate)), rig, layout)  # the first second is the neutral
    frames = int(opts.get("--frames", take.n_frames))
    stats = livecap.Session(take.slice(0, frames), livecap.Solver(profile, mode="robust"), [JawOpenEvents()]).run()
    print(f"frames in {stats['frames_in']}, out {stats['frames_out']}, "
          f"solve p50 {stats['timing']['solve']['p50_ms']:.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
