"""Ordered thread pipelines: the one helper behind the reader's decode threads and the labeller's worker thread."""
from __future__ import annotations

import collections
import concurrent.futures
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int, in_flight: int | None = None
                ) -> Iterator[tuple[T, R]]:
    """Yields `(item, fn(item))` in the order of `items`, with `fn` running on `workers` threads.

    At most `in_flight` items (default: `workers`) wait beyond the one being yielded, so memory stays bounded. `items`
    is drawn on the caller's thread, so it may carry state from one item to the next. An exception raised by `fn`
    surfaces when its item's turn comes; an exception raised while drawing from `items` (e.g. a truncated file)
    surfaces after the results of every item drawn before it, as a sequential loop would have it.
    """
    workers = max(1, int(workers))
    in_flight = max(1, workers if in_flight is None else int(in_flight))
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        pending: collections.deque = collections.deque()
        source = iter(items)
        draw_error = None
        while True:
            try:
                item = next(source)
            except StopIteration:
                break
            except Exception as err:  # noqa: BLE001 - re-raised below, after the earlier items' results
                draw_error = err
                break
            pending.append((item, pool.submit(fn, item)))
            if len(pending) > in_flight:
                done, future = pending.popleft()
                yield done, future.result()
        while pending:
            done, future = pending.popleft()
            yield done, future.result()
        if draw_error is not None:
            raise draw_error
