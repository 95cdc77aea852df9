"""A pipeline stage on a thread of its own, feeding its consumer through a bounded queue.

Used by the front-end's prefetch (:class:`dhptam.frontend.Frontend`) and by the run's
front-end and extraction stages (:mod:`dhptam.run`).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator, Iterator
from typing import Any


class _Stop:
    """End of a stage's stream."""


class _Failure:
    def __init__(self, error: BaseException) -> None:
        self.error = error


def prefetched(
    source: Iterator[Any], work: Callable[[Any], Any], name: str, depth: int
) -> Generator[Any, None, None]:
    """Runs ``work`` over ``source`` on a thread of its own, up to ``depth`` items ahead of the
    consumer. Errors are re-raised in the consumer; closing the generator (or an exception in
    the consumer) stops the thread and closes ``source`` in turn."""
    q: queue.Queue[Any] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item: Any) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in source:
                if stop.is_set() or not put(work(item)):
                    return
            put(_Stop())
        except BaseException as error:  # handed to the consumer
            put(_Failure(error))

    thread = threading.Thread(target=produce, name=f"dhptam-{name}", daemon=True)
    thread.start()
    try:
        while True:
            try:
                item = q.get(timeout=0.1)
            except queue.Empty:
                if not thread.is_alive() and q.empty():
                    return
                continue
            if isinstance(item, _Stop):
                return
            if isinstance(item, _Failure):
                raise item.error
            yield item
    finally:
        stop.set()
        thread.join(timeout=30)
        close = getattr(source, "close", None)
        if close is not None and not thread.is_alive():
            close()
