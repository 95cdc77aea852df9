"""Events/s read from each dataset format: dhptam's readers against the plain library path.

Writes, in a temporary folder, one event stream per format at 2 M events/s:

* VECtor ``*.synced.left_event.hdf5``: u16/u16/u8/u32 columns + ``/t_offset`` + ``/ms_to_idx``,
  zstd (hdf5plugin), 16 Ki-event chunks;
* MVSEC ``*_data.hdf5``: ``davis/left/events`` (N, 4) float64, Blosc, 16 Ki-row chunks;
* a VECtor ROS1 bag: ``/prophesee/left/events`` ``dvs_msgs/EventArray`` messages of
  ``--per-message`` events, LZ4 chunks (rosbags' writer);

then reads every event once with

* dhptam: ``stream.iter_windows(50 ms)`` over the whole file (bounded memory; for the bag this
  includes the indexing pass at open),
* the plain library path a user writes without dhptam: h5py reading the whole columns at once
  (plus the unit conversion to ns), and rosbags' ``Reader.messages`` + ``deserialize_ros1``
  collecting the events into numpy arrays.

Both results are checked equal. Prints a Markdown table for docs/BENCHMARKS.md.

    python benches/bench_datasets.py [--seconds 2] [--bag-seconds 0.5] [--per-message 20000]
"""

from __future__ import annotations

import argparse
import itertools
import platform
import tempfile
import time
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np

RATE = 2_000_000
W, H = 640, 480
OFFSET_US = 1_643_091_527_000_000
WINDOW_NS = 50_000_000


def events(n: int, seconds: float, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "x": rng.integers(0, W, n).astype(np.uint16),
        "y": rng.integers(0, H, n).astype(np.uint16),
        "t": np.sort(rng.integers(0, int(seconds * 1e6), n)).astype(np.int64),
        "p": rng.integers(0, 2, n).astype(np.uint8),
    }


def write_vector(path: Path, ev: dict[str, np.ndarray]) -> None:
    zstd = hdf5plugin.Zstd()
    with h5py.File(path, "w") as f:
        for k, dtype in (("x", np.uint16), ("y", np.uint16), ("p", np.uint8), ("t", np.uint32)):
            f.create_dataset(f"events/{k}", data=ev[k].astype(dtype), chunks=(1 << 14,), **zstd)
        f.create_dataset("t_offset", data=np.int64(OFFSET_US))
        ms = np.searchsorted(ev["t"], 1000 * np.arange(int(ev["t"][-1]) // 1000 + 2)).astype(np.uint64)
        f.create_dataset("ms_to_idx", data=ms, **zstd)


def write_mvsec(path: Path, ev: dict[str, np.ndarray]) -> None:
    t_s = (ev["t"] + OFFSET_US) * 1e-6
    rows = np.column_stack([ev["x"], ev["y"], t_s, np.where(ev["p"] > 0, 1.0, -1.0)]).astype(np.float64)
    with h5py.File(path, "w") as f:
        f.create_dataset("davis/left/events", data=rows, chunks=(1 << 14, 4), **hdf5plugin.Blosc())


def write_bag(path: Path, ev: dict[str, np.ndarray], per_message: int) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from dhptam.datasets.rosbag import EVENT_DTYPE

    store = get_typestore(Stores.ROS1_NOETIC)
    types = dict(
        get_types_from_msg(
            "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n",
            "dvs_msgs/msg/EventArray",
        )
    )
    types.update(get_types_from_msg("uint16 x\nuint16 y\ntime ts\nbool polarity\n", "dvs_msgs/msg/Event"))
    store.register(types)
    t_ns = (ev["t"] + OFFSET_US) * 1000
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    with writer:
        conn = writer.add_connection("/prophesee/left/events", "dvs_msgs/msg/EventArray", typestore=store)
        for k, a in enumerate(range(0, len(t_ns), per_message)):
            b = min(a + per_message, len(t_ns))
            rec = np.empty(b - a, EVENT_DTYPE)
            rec["x"], rec["y"], rec["p"] = ev["x"][a:b], ev["y"][a:b], ev["p"][a:b]
            rec["sec"], rec["nsec"] = t_ns[a:b] // 10**9, t_ns[a:b] % 10**9
            last = int(t_ns[b - 1])
            head = np.array([k, last // 10**9, last % 10**9, 4], "<u4").tobytes() + b"left"
            body = np.array([H, W, b - a], "<u4").tobytes() + rec.tobytes()
            writer.write(conn, last + 1000, head + body)


def dhptam_read(stream: object) -> tuple[int, int]:
    n, checksum = 0, 0
    for w in stream.iter_windows(WINDOW_NS):  # type: ignore[attr-defined]
        n += len(w)
        checksum += int(w.t_ns.sum() % 1_000_003) + int(w.x.sum())
    return n, checksum


def checksum_of(x: np.ndarray, t_ns: np.ndarray) -> int:
    # Same fold as dhptam_read, over the same 50 ms windows.
    edges = np.searchsorted(t_ns, np.arange(int(t_ns[0]), int(t_ns[-1]) + WINDOW_NS + 1, WINDOW_NS))
    total = 0
    for a, b in itertools.pairwise(edges):
        total += int(t_ns[a:b].sum() % 1_000_003) + int(x[a:b].astype(np.int64).sum())
    return total


def timed(fn: object, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()  # type: ignore[operator]
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=2.0, help="HDF5 recordings, seconds at 2 M ev/s")
    ap.add_argument("--bag-seconds", type=float, default=0.5, help="bag recording, seconds at 2 M ev/s")
    ap.add_argument("--per-message", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    from dhptam.datasets import EventSource
    from dhptam.datasets.mvsec import MvsecEventSource
    from dhptam.datasets.rosbag import BagEventStream, BagFile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        ev = events(int(RATE * args.seconds), args.seconds, 0)
        n = len(ev["t"])
        vec = d / "seq.synced.left_event.hdf5"
        write_vector(vec, ev)
        mv = d / "seq_data.hdf5"
        write_mvsec(mv, ev)

        def vector_dhptam() -> tuple[int, int]:
            with EventSource(vec) as s:
                return dhptam_read(s)

        def vector_h5py() -> tuple[int, int]:
            with h5py.File(vec) as f:
                x = f["events/x"][:]
                _ = f["events/y"][:], f["events/p"][:]
                t_ns = (f["events/t"][:].astype(np.int64) + int(f["t_offset"][()])) * 1000
            return len(t_ns), checksum_of(x, t_ns)

        def mvsec_dhptam() -> tuple[int, int]:
            with MvsecEventSource(mv, "left") as s:
                return dhptam_read(s)

        def mvsec_h5py() -> tuple[int, int]:
            with h5py.File(mv) as f:
                rows_ = f["davis/left/events"][:]
            t_ns = np.rint(rows_[:, 2] * 1e6).astype(np.int64) * 1000
            return len(t_ns), checksum_of(rows_[:, 0].astype(np.uint16), t_ns)

        for name, ours, plain, base in (
            ("VECtor HDF5 (zstd)", vector_dhptam, vector_h5py, "h5py, whole columns"),
            ("MVSEC HDF5 (N×4 float64, Blosc)", mvsec_dhptam, mvsec_h5py, "h5py, whole dataset"),
        ):
            t_ours, r_ours = timed(ours, args.repeat)
            t_plain, r_plain = timed(plain, args.repeat)
            assert r_ours == r_plain, (name, r_ours, r_plain)
            rows.append((name, n, t_ours, base, t_plain))

        bev = events(int(RATE * args.bag_seconds), args.bag_seconds, 1)
        nb = len(bev["t"])
        bag = d / "seq.bag"
        write_bag(bag, bev, args.per_message)

        def bag_dhptam() -> tuple[int, int]:
            f = BagFile(bag)
            try:
                return dhptam_read(BagEventStream(f, "/prophesee/left/events"))
            finally:
                f.close()

        def bag_rosbags() -> tuple[int, int]:
            from rosbags.rosbag1 import Reader
            from rosbags.typesys import Stores, get_types_from_msg, get_typestore

            store = get_typestore(Stores.ROS1_NOETIC)
            with Reader(bag) as reader:
                conn = reader.connections[0]
                store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
                xs, ts = [], []
                for c, _, raw in reader.messages([conn]):
                    msg = store.deserialize_ros1(raw, c.msgtype)
                    xs.append(np.fromiter((e.x for e in msg.events), np.uint16, len(msg.events)))
                    ts.append(
                        np.fromiter(
                            (e.ts.sec * 10**9 + e.ts.nanosec for e in msg.events), np.int64, len(msg.events)
                        )
                    )
                    _ = [(e.y, e.polarity) for e in msg.events]
            t_ns = np.concatenate(ts)
            return len(t_ns), checksum_of(np.concatenate(xs), t_ns)

        t_ours, r_ours = timed(bag_dhptam, args.repeat)
        t_plain, r_plain = timed(bag_rosbags, 1)
        assert r_ours == r_plain, ("bag", r_ours, r_plain)
        rows.append(("VECtor ROS1 bag (LZ4)", nb, t_ours, "rosbags deserialize_ros1", t_plain))

    print(f"python {platform.python_version()}, {platform.machine()}, best of {args.repeat}")
    print("| format | events | dhptam 50 ms windows | M ev/s | baseline | baseline time | M ev/s | ratio |")
    print("|---|---:|---:|---:|---|---:|---:|---:|")
    for name, count, t_ours, base, t_plain in rows:
        print(
            f"| {name} | {count:,} | {t_ours:.3f} s | {count / t_ours / 1e6:.1f} | {base} | "
            f"{t_plain:.3f} s | {count / t_plain / 1e6:.2f} | {t_plain / t_ours:.2f}× |"
        )


if __name__ == "__main__":
    main()
