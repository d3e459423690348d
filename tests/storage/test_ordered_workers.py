"""OrderedWorkers: work on several threads, results delivered in submission order."""

from __future__ import annotations

import threading
import time

import pytest

from stipi_daemon.storage.ordered_workers import OrderedWorkers


def _slow_for_even(item: int) -> int:
    """Even items take longer: the odd worker finishes its items first."""
    time.sleep(0.004 if item % 2 == 0 else 0.0)
    return item * item


def test_results_come_in_submission_order_from_every_worker() -> None:
    delivered: list[tuple[int, int]] = []
    worked_on: dict[int, str] = {}

    def work(item: int) -> int:
        worked_on[item] = threading.current_thread().name
        return _slow_for_even(item)

    workers: OrderedWorkers[int, int] = OrderedWorkers(
        [work, work],
        lambda item, result: delivered.append((item, result)),
        lambda exc: pytest.fail(f"no error expected: {exc!r}"),
        capacity=4,
        name="test",
    )
    assert all(workers.submit(k, wait_s=5.0) for k in range(60))
    workers.close()
    # the odd items finish first, yet every result comes in submission order
    assert delivered == [(k, k * k) for k in range(60)]
    assert {worked_on[k] for k in range(0, 60, 2)} == {"test 0"}  # round-robin
    assert {worked_on[k] for k in range(1, 60, 2)} == {"test 1"}


def test_a_full_queue_leaves_the_item_out_unless_the_caller_waits() -> None:
    gate = threading.Event()
    delivered: list[int] = []

    def blocked(item: int) -> int:
        gate.wait(5.0)
        return item

    workers: OrderedWorkers[int, int] = OrderedWorkers(
        [blocked], lambda i, r: delivered.append(r), lambda exc: None, capacity=2, name="t"
    )
    taken = [workers.submit(k) for k in range(6)]
    # one in the worker's hands, two waiting: the rest are refused at once
    assert taken[:3] == [True, True, True] or taken[:2] == [True, True]
    assert not all(taken)
    gate.set()
    assert workers.submit(100, wait_s=5.0)  # room comes as the worker proceeds
    workers.close()
    assert delivered == [k for k, ok in zip(range(6), taken, strict=True) if ok] + [100]


def test_the_first_failure_is_reported_once_and_later_items_are_refused() -> None:
    errors: list[BaseException] = []
    delivered: list[int] = []

    def work(item: int) -> int:
        if item == 3:
            raise OSError("disk full")
        return item

    workers: OrderedWorkers[int, int] = OrderedWorkers(
        [work, work], lambda i, r: delivered.append(r), errors.append, capacity=2, name="t"
    )
    for k in range(6):
        workers.submit(k, wait_s=5.0)
    deadline = time.monotonic() + 5.0
    while workers.failed is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not workers.submit(7, wait_s=5.0)  # never waits on a failed pipeline
    workers.close()
    assert len(errors) == 1 and str(errors[0]) == "disk full"
    # in order, and nothing from the failed item on (an item before it that finished after
    # the failure is not delivered either: recording has stopped)
    assert delivered == list(range(len(delivered))) and len(delivered) <= 3


def test_no_worker_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one worker"):
        OrderedWorkers([], lambda i, r: None, lambda e: None, capacity=1, name="t")
