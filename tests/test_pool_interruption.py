"""An interruption (Ctrl-C; SIGTERM in the CLI) raised into the thread waiting on a pool leaves no pool blocked.

CI once saw ``make-dataset`` given SIGTERM right as a shard finished never exit: ``concurrent.futures.wait`` takes
the pending futures' locks one after the other, an interruption between two left locks held, the pool's manager
thread blocked for ever on the next finished shard, and the interpreter's exit joined it. Signals are raised
between bytecodes, so these tests raise ``KeyboardInterrupt`` at every bytecode of the wait in turn (a trace
function, in a subprocess that a watchdog ends if anything blocks) and check that every job's future is still
completed by its pool thread, and that the call returns. The pool's own set-up, ``submit``, ``add_done_callback``
and ``shutdown`` are not interrupted here: they take locks too, whatever the caller does (see ``evnoise._pool``).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

#: the fault injection: prints ``ok: N`` (N interruption points, all survived) or ``hang: ...``
SCRIPT = textwrap.dedent("""
    import os, sys, threading, time
    from concurrent.futures import Future, ThreadPoolExecutor

    from evnoise import _pool

    TARGET = sys.argv[1]
    # the pool's own set-up and shutdown, not the waiting: interrupted, they can block (Python's hazard, not ours)
    POOL_OWN = {ThreadPoolExecutor.__init__.__code__, ThreadPoolExecutor.submit.__code__,
                ThreadPoolExecutor.shutdown.__code__, Future.add_done_callback.__code__}
    PATIENCE_S = 30.0
    started = [time.monotonic(), "start"]


    def watchdog():
        while True:
            time.sleep(0.5)
            if time.monotonic() - started[0] > PATIENCE_S:
                print(f"hang: {started[1]}", flush=True)
                os._exit(1)


    threading.Thread(target=watchdog, daemon=True).start()


    class Recording(ThreadPoolExecutor):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.futures = []

        def submit(self, *args, **kwargs):
            fut = super().submit(*args, **kwargs)
            self.futures.append(fut)
            return fut


    def job(x):
        time.sleep(0.0003 * (x % 3))
        return x


    def where(frame):
        parts = []
        while frame is not None:
            parts.append(f"{os.path.basename(frame.f_code.co_filename)}:{frame.f_lineno} {frame.f_code.co_name}")
            frame = frame.f_back
        return " <- ".join(parts)


    def pools_own(frame):
        while frame is not None:
            if frame.f_code in POOL_OWN:
                return True
            frame = frame.f_back
        return False


    def run(at):
        pool = Recording(max_workers=2) if TARGET == "collect" else None
        state = {"count": 0, "fired": None}

        def tracer(frame, event, arg):
            if state["fired"] is not None:
                return None
            if event == "call" and pools_own(frame):
                return None
            frame.f_trace_opcodes = True
            state["count"] += 1
            if state["count"] == at:
                state["fired"] = where(frame)
                started[1] = f"interrupted at bytecode {at} ({state['fired']}): the call never returned"
                raise KeyboardInterrupt
            return tracer

        started[:] = [time.monotonic(), f"bytecode {at} not reached; the previous interruption: {started[1]}"]
        sys.settrace(tracer)
        try:
            if TARGET == "collect":
                got = []
                _pool.collect_results(pool, job, range(6), got.append)
                assert sorted(got) == list(range(6)), got
            else:
                assert _pool.map_in_threads(lambda a, b: a * b, [(i, 2) for i in range(6)], 2) == [0, 2, 4, 6, 8, 10]
        except KeyboardInterrupt:
            pass
        finally:
            sys.settrace(None)
        started[1] = f"interrupted at bytecode {at} ({state['fired']}): a pool thread is blocked"
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
            for fut in pool.futures:
                while not fut.done():
                    time.sleep(0.0002)
            pool.shutdown(wait=True)
        return state["fired"] is not None


    at = 1
    while run(at):
        at += 1
    print(f"ok: {at - 1}", flush=True)
""")


def _inject(target: str) -> int:
    done = subprocess.run([sys.executable, "-c", SCRIPT, target], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.startswith("ok: "), done.stdout + done.stderr
    return int(done.stdout.split()[1])


def test_interrupting_collect_results_at_every_bytecode_leaves_no_pool_thread_blocked():
    # make-dataset's wait for its shards (was concurrent.futures.wait: blocked at the first points in its lock loop)
    assert _inject("collect") > 100


def test_interrupting_map_in_threads_at_every_bytecode_returns():
    # the simulator's and the gzip writer's waits on their thread pools
    assert _inject("map") > 100
