"""Waiting on thread and process pools so that an interruption cannot leave them blocked (internal).

A signal handler's exception (Ctrl-C; SIGTERM in the CLI, see :mod:`evnoise.cli`) is raised in the main thread
between two bytecodes, and that can be right after a lock was taken and before the ``with`` that would release
it begins (CPython issue 29988). A :class:`concurrent.futures.Future`'s lock left held that way blocks, for ever,
the pool thread that completes the future, and then whoever joins that thread: the pool's shutdown, or the
interpreter's exit (``concurrent.futures`` joins its threads there). ``Future.result`` and
``concurrent.futures.wait`` take those locks in the waiting thread (``wait`` takes every pending future's, one
after the other, in Python code): a ``make-dataset`` run given SIGTERM just as a shard finished never exited.

Here the pool's own thread reads each future's outcome (a done callback) and hands it over through a
:class:`queue.SimpleQueue`, whose ``get`` is one C call that holds nothing a pool thread needs. The waiting
thread takes no pool lock; submitting (and cancelling after an error) still takes them briefly.
"""

from __future__ import annotations

import queue
from concurrent.futures import ThreadPoolExecutor


def _outcome(future) -> tuple:
    try:
        return future.result(), None
    except BaseException as exc:  # the job's exception, or the future's own (cancelled, pool broken)
        return None, exc


def hand_over(future, channel: queue.SimpleQueue | None = None) -> queue.SimpleQueue:
    """The queue that receives ``future``'s outcome, ``(result, None)`` or ``(None, exception)``, put there by
    the thread that completes it (a new queue unless ``channel`` is given)."""
    channel = queue.SimpleQueue() if channel is None else channel
    future.add_done_callback(lambda done: channel.put(_outcome(done)))
    return channel


def take(channel: queue.SimpleQueue):
    """The next outcome in ``channel``: its result, or its exception raised here."""
    result, error = channel.get()
    if error is not None:
        raise error
    return result


def map_in_threads(fn, tasks, threads: int) -> list:
    """``fn(*task)`` for every task, in task order (threads only change speed)."""
    tasks = list(tasks)
    if threads <= 1 or len(tasks) <= 1:
        return [fn(*t) for t in tasks]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        channels = [hand_over(pool.submit(fn, *t)) for t in tasks]
        try:
            return [take(c) for c in channels]
        except BaseException:  # the tasks not yet started are not run
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def collect_results(pool, fn, jobs, finished) -> None:
    """Submit ``fn(job)`` to ``pool`` (a :mod:`concurrent.futures` executor) for each of ``jobs`` and pass each
    result to ``finished`` as soon as it is ready, in the order they complete; a job's exception is raised here."""
    completed = queue.SimpleQueue()
    submitted = 0
    for job in jobs:
        hand_over(pool.submit(fn, job), completed)
        submitted += 1
    for _ in range(submitted):
        finished(take(completed))
