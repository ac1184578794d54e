"""ordered_map: input order kept, errors where a sequential loop would raise them, bounded look-ahead."""
import threading
import time

import pytest

from ff3d_tf.parallel import ordered_map


def test_order_kept_with_uneven_work():
    # Later items finish first (shorter sleeps); the output order must still be the input order.
    out = list(ordered_map(lambda i: (time.sleep(0.002 * (10 - i)), i * i)[1], range(10), workers=3, in_flight=4))
    assert out == [(i, i * i) for i in range(10)]


def test_draw_error_after_earlier_results_and_fn_error_in_turn():
    def items():
        yield from range(4)
        raise OSError("truncated")

    got = []
    with pytest.raises(OSError, match="truncated"):
        for item, result in ordered_map(lambda i: -i, items(), workers=2):
            got.append(result)
    assert got == [0, -1, -2, -3]  # every result drawn before the error came out first

    def fails_on_two(i):
        if i == 2:
            raise ValueError("bad item 2")
        return i

    got = []
    with pytest.raises(ValueError, match="bad item 2"):
        for _, result in ordered_map(fails_on_two, range(6), workers=2):
            got.append(result)
    assert got == [0, 1]


def test_look_ahead_is_bounded():
    drawn, lock = [], threading.Lock()

    def items():
        for i in range(20):
            with lock:
                drawn.append(i)
            yield i

    for item, _ in ordered_map(lambda i: i, items(), workers=2, in_flight=3):
        with lock:
            # When item k is yielded, at most k + in_flight + 1 items have been drawn (k itself, 3 waiting, 1 more).
            assert len(drawn) <= item + 1 + 3 + 1
