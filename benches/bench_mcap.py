"""MCAP event throughput: dhptam's Rust writer/reader against the Python ``mcap`` library.

Generates ``--events`` events (20 M events/s, random pixels of a 1280×720 sensor, sorted
times), then, in the same run and on the same data:

* writes them as ``dhptam.EventBatch`` messages (32768 events a batch, zstd chunks of 4 MiB)
  with dhptam's ``McapWriter`` and with the Python ``mcap`` library's ``Writer`` (payloads
  built by the protobuf class generated from dhptam's own schema, the columns passed as
  bytes: the plain-library path a user would write),
* reads every event back with dhptam's ``McapReader.event_slice`` and with ``mcap``'s
  ``make_reader().iter_messages()`` + protobuf decode + ``np.frombuffer`` + concatenate,
* reads ``--windows`` random 50 ms windows with dhptam (index lookup + decode of the batches
  involved) and with ``mcap``'s ``iter_messages(start_time, end_time)`` over the batches
  overlapping the window, trimmed with ``np.searchsorted``.

Each read is checked against the generated events. Throughput counts the raw event payload
(13 bytes an event: x, y uint16, t int64, p int8). Prints a Markdown table.

    python benches/bench_mcap.py [--events 20e6] [--windows 30] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

BATCH = 32768
CHUNK = 4 << 20
RATE = 20e6


def make_events(n: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(0)
    t = 1_000_000_000 + np.cumsum(rng.exponential(1e9 / RATE, n)).astype(np.int64)
    x = rng.integers(0, 1280, n).astype(np.uint16)
    y = rng.integers(0, 720, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.int8)
    return x, y, t, p


def batch_class() -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    from dhptam._core import McapWriter

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "schema.mcap"
        w = McapWriter(path)
        one = np.zeros(1, np.uint16)
        w.add_events("/e", "e", one, one, np.ones(1, np.int64), np.zeros(1, np.int8))
        w.finish()
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None
        schema = next(iter(summary.schemas.values()))
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for file in fds.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("dhptam.EventBatch")), schema.data


def write_dhptam(path: Path, ev: tuple[np.ndarray, ...]) -> None:
    from dhptam._core import McapWriter

    x, y, t, p = ev
    w = McapWriter(path, compression="zstd", chunk_size_bytes=CHUNK, batch_events=BATCH)
    block = 1 << 20
    for i in range(0, len(t), block):
        w.add_events(
            "/events/left",
            "event_left",
            x[i : i + block],
            y[i : i + block],
            t[i : i + block],
            p[i : i + block],
        )
    w.finish()


def write_python(path: Path, ev: tuple[np.ndarray, ...], cls: Any, schema_data: bytes) -> None:
    from mcap.writer import CompressionType, Writer

    x, y, t, p = ev
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=CHUNK, compression=CompressionType.ZSTD)
        w.start(profile="dhptam", library="python-mcap")
        sid = w.register_schema("dhptam.EventBatch", "protobuf", schema_data)
        cid = w.register_channel("/events/left", "protobuf", sid, {"batch_events": str(BATCH)})
        for k, i in enumerate(range(0, len(t), BATCH)):
            j = min(i + BATCH, len(t))
            m = cls(
                count=j - i,
                x=x[i:j].tobytes(),
                y=y[i:j].tobytes(),
                t_ns=t[i:j].tobytes(),
                p=p[i:j].tobytes(),
                first_index=i,
            )
            m.timestamp.FromNanoseconds(int(t[i]))
            m.frame_id = "event_left"
            w.add_message(
                cid, log_time=int(t[i]), data=m.SerializeToString(), publish_time=int(t[i]), sequence=k
            )
        w.finish()


def decode_python(messages: Any, cls: Any) -> tuple[np.ndarray, ...]:
    cols: list[list[np.ndarray]] = [[], [], [], []]
    for _, _, message in messages:
        b = cls.FromString(message.data)
        cols[0].append(np.frombuffer(b.x, "<u2"))
        cols[1].append(np.frombuffer(b.y, "<u2"))
        cols[2].append(np.frombuffer(b.t_ns, "<i8"))
        cols[3].append(np.frombuffer(b.p, "i1"))
    return tuple(np.concatenate(c) if c else np.empty(0) for c in cols)


def read_all_python(path: Path, cls: Any) -> tuple[np.ndarray, ...]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return decode_python(make_reader(f).iter_messages(topics=["/events/left"]), cls)


def read_all_dhptam(path: Path) -> tuple[np.ndarray, ...]:
    from dhptam._core import McapReader

    r = McapReader(path)
    return r.event_slice("/events/left", 0, r.event_count("/events/left"))


def best(fn: Any, repeat: int) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--windows", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    n = int(args.events)
    ev = make_events(n)
    cls, schema_data = batch_class()
    raw_mb = 13 * n / 1e6
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        a, b = Path(tmp) / "dhptam.mcap", Path(tmp) / "python.mcap"
        tw_d, _ = best(lambda: write_dhptam(a, ev), args.repeat)
        tw_p, _ = best(lambda: write_python(b, ev, cls, schema_data), args.repeat)
        size_d, size_p = os.path.getsize(a), os.path.getsize(b)
        tr_d, got_d = best(lambda: read_all_dhptam(a), args.repeat)
        tr_p, got_p = best(lambda: read_all_python(a, cls), args.repeat)
        for got in (got_d, got_p):
            for col, ref in zip(got, ev, strict=True):
                assert np.array_equal(col, ref), "read-back mismatch"

        # 50 ms windows at random times.
        from mcap.reader import make_reader

        from dhptam._core import McapReader

        rng = np.random.default_rng(1)
        t = ev[2]
        starts = rng.integers(int(t[0]), int(t[-1]) - 50_000_000, args.windows)
        reader = McapReader(a)

        def windows_dhptam() -> int:
            total = 0
            for s in starts:
                i0, i1 = reader.event_index_range("/events/left", int(s), int(s) + 50_000_000)
                total += len(reader.event_slice("/events/left", i0, i1)[2])
            return total

        batch_t0 = t[::BATCH]

        def windows_python() -> int:
            total = 0
            with open(a, "rb") as f:
                r = make_reader(f)
                for s in starts:
                    e = int(s) + 50_000_000
                    # The batch holding s starts before s: begin at that batch's log time.
                    k = max(int(np.searchsorted(batch_t0, s, side="right")) - 1, 0)
                    found = r.iter_messages(
                        topics=["/events/left"], starting_at=int(batch_t0[k]), ending_before=e
                    )
                    cols = decode_python(found, cls)
                    tt = cols[2]
                    total += int(np.searchsorted(tt, e) - np.searchsorted(tt, s))
            return total

        tw50_d, n_d = best(windows_dhptam, args.repeat)
        tw50_p, n_p = best(windows_python, args.repeat)
        expected = int(sum(np.searchsorted(t, s + 50_000_000) - np.searchsorted(t, s) for s in starts))
        assert n_d == n_p == expected, (n_d, n_p, expected)

    def row(what: str, td: float, tp: float, extra: str = "") -> None:
        rows.append(
            f"| {what} | {n / td / 1e6:.1f} M ev/s ({raw_mb / td:.0f} MB/s) | {n / tp / 1e6:.1f} M ev/s "
            f"({raw_mb / tp:.0f} MB/s) | {tp / td:.1f}× |{extra}"
        )

    print(
        f"{n / 1e6:.0f} M events ({raw_mb:.0f} MB raw), "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"
    )
    print(
        f"file size: dhptam {size_d / 1e6:.1f} MB ({8 * size_d / n:.1f} bit/event), "
        f"python mcap {size_p / 1e6:.1f} MB"
    )
    print("| operation | dhptam (Rust) | Python `mcap` | ratio |")
    print("|---|---|---|---|")
    row("write, zstd", tw_d, tw_p)
    row("read all", tr_d, tr_p)
    for r in rows:
        print(r)
    ms = 1e3 / args.windows
    print(
        f"| 50 ms windows (1 M events each), {args.windows} at random times | {tw50_d * ms:.1f} ms/window | "
        f"{tw50_p * ms:.1f} ms/window | {tw50_p / tw50_d:.1f}× |"
    )


if __name__ == "__main__":
    main()
