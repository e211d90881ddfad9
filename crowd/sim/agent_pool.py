"""Worker processes that step ranges of the crowd's agents, over shared memory.

Why processes and not threads: a numpy call holds the GIL while Python dispatches it, and at the
AI's array sizes (a few thousand to a hundred thousand agents a range) the dispatch is most of a
call, so threads over tiles gave 10 to 30 % on 2 threads and nothing beyond (docs/BENCHMARKS.md).
Processes each have their own interpreter: the same ~20-operation kernel over 100,000 agents took
9.2 ms in one process and 1.4 ms in 16 (1,000,000: 151 -> 11 ms), on the H200 machine's host.

The crowd's arrays live in one shared-memory block (``SharedArrays``); a worker maps the same block
and steps agents lo..hi of it through the AI's own range methods, so the arithmetic is the one the
main process runs. A substep is a few phases with a barrier between them (``AgentPool.run``): the
main process posts the phase's numbers in a small shared array, wakes each worker through its
semaphore, steps range 0 itself, and waits on one semaphore the workers release when done. Rare
messages (new arrays after a resize, new settings) go through a pipe.

Every object here is released on every path: ``AgentPool.close`` stops and joins the workers and
unlinks the blocks, a finalizer does it if the pool is dropped, and a worker that exits or fails is
one line (an AIError) in the main process, never a hang.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import traceback
import types
import weakref
from multiprocessing import shared_memory

import numpy as np
from ..errors import CrowdError

PARAMS = 64  # float64 numbers a phase is posted with (its code first)
RESULTS = 8  # float64 numbers a worker answers a phase with (its status first)
STOP, SYNC = -1, 0  # phase codes of the pool's own; the AI's phases are 1, 2, ...
WAIT_SLICE_S = 0.5  # how often a waiting main process checks that its workers are still running
START_TIMEOUT_S = 120.0  # a worker that has not started by then (an overloaded machine) is an error


class PoolError(CrowdError, RuntimeError):
    """A worker failed or exited; the message is one line."""


def available_cores() -> int:
    """Cores this process may run on (taskset and cgroups included where the OS says so)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


class SharedArrays:
    """Named numpy arrays in one shared-memory block. ``layout``: name -> (dtype, shape); the block is
    created here (``name`` None) or mapped (a worker). Arrays start 64-byte aligned."""

    def __init__(self, layout: dict, name: str | None = None):
        offsets, size = {}, 0
        for key, (dtype, shape) in layout.items():
            offsets[key] = size
            size += -(-int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize // 64) * 64
        self.layout = dict(layout)
        self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=max(size, 64))
        # np.frombuffer (not np.ndarray(buffer=...)) holds an export of the mapping, so closing the block
        # while an array of it is still alive leaves the mapping to that array instead of unmapping it
        # under its feet (a segfault at its next use).
        self.arrays = {key: np.frombuffer(self.shm.buf, dtype, int(np.prod(shape, dtype=np.int64)), offsets[key]).reshape(shape)
                       for key, (dtype, shape) in layout.items()}
        self._owner = name is None  # a new block is zero-filled by the OS
        self._finalizer = weakref.finalize(self, SharedArrays._release, self.shm, self._owner)

    @property
    def name(self) -> str:
        return self.shm.name

    def close(self) -> None:
        """Unmap (and, for the creator, unlink); also done when the object is collected. Views still
        held elsewhere keep the mapping alive until they go; the name is gone at once."""
        self.arrays = {}
        self._finalizer()

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive

    @staticmethod
    def _release(shm, owner: bool) -> None:
        try:
            shm.close()
        except BufferError:  # an array of the block is still alive somewhere: the mapping goes with the last one
            shm._mmap = None  # (and SharedMemory's own __del__ must not try again)
        if owner:
            try:
                shm.unlink()
            except FileNotFoundError:
                pass


def _serve(index: int, go, done, params_name: str, results_name: str, conn, make_stepper) -> None:
    """A worker's loop: wait for a phase, run it on this worker's range, answer. `make_stepper()` makes
    the object whose ``sync_worker(message)`` maps the arrays and whose ``run_phase(code, params,
    index)`` steps them (the AI, which this module does not import)."""
    from ..allocator import keep_freed_memory

    # Ctrl-C in a terminal reaches the whole process group: the main process handles it (and closes the
    # pool); a worker printing its own KeyboardInterrupt traceback would only be noise.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    keep_freed_memory()  # the same malloc settings as the main process: 4x faster numpy temporaries
    control = SharedArrays({"params": (np.float64, (PARAMS,))}, params_name)
    results_block = SharedArrays({"results": (np.float64, (index + 1, RESULTS))}, results_name)  # a prefix of the main's
    params, answer = control.arrays["params"], results_block.arrays["results"][index]
    stepper = None
    while True:
        go.acquire()
        code = int(params[0])
        if code == STOP:
            break
        try:
            if code == SYNC:
                message = conn.recv()
                if stepper is None:
                    stepper = make_stepper()
                stepper.sync_worker(message)
                answer[:] = 0.0
            else:
                answer[:] = 0.0
                numbers = stepper.run_phase(code, params, index)
                answer[1:1 + len(numbers)] = numbers
            answer[0] = 1.0
        except BaseException as error:  # any failure is the main process's one line, not a silent hang
            answer[0] = -1.0
            line = f"{type(error).__name__}: {error}".splitlines()[0] if str(error) else traceback.format_exc().splitlines()[-1]
            try:
                conn.send(line)
            except OSError:
                pass
        done.release()
    if stepper is not None:
        stepper.sync_worker(None)
    control.close()
    results_block.close()
    conn.close()


class AgentPool:
    """``workers`` processes (ranges 1..workers of a phase; the main process steps range 0), each
    stepping through the object `make_stepper` (a picklable callable) makes in it."""

    def __init__(self, workers: int, make_stepper):
        self.workers = int(workers)
        ctx = mp.get_context("spawn")  # no fork: the main process may hold a GL context and driver threads
        self._control = SharedArrays({"params": (np.float64, (PARAMS,))})
        self._results = SharedArrays({"results": (np.float64, (self.workers, RESULTS))})
        self.params = self._control.arrays["params"]
        self.results = self._results.arrays["results"]
        self._done = ctx.Semaphore(0)
        self._go = [ctx.Semaphore(0) for _ in range(self.workers)]
        self._conns, self._procs = [], []
        self._finalizer = weakref.finalize(self, AgentPool._shutdown, self._procs, self._go, self.params, self._conns,
                                           self._control, self._results)
        # A spawned child runs the parent's main script again (as __mp_main__) unless that script guards
        # itself with `if __name__ == "__main__"`; the workers need nothing from it (their code is this
        # module), so while they start the main module is one with no file, as in an interactive session.
        main = sys.modules["__main__"]
        sys.modules["__main__"] = types.ModuleType("__main__")
        try:
            for w in range(self.workers):
                mine, theirs = ctx.Pipe()
                proc = ctx.Process(target=_serve, args=(w, self._go[w], self._done, self._control.name, self._results.name, theirs,
                                                             make_stepper),
                                   name=f"crowd-ai-{w + 1}", daemon=True)
                proc.start()
                theirs.close()
                self._conns.append(mine)
                self._procs.append(proc)
        except BaseException:
            self.close()
            raise
        finally:
            sys.modules["__main__"] = main

    def sync(self, messages: list, timeout: float = START_TIMEOUT_S) -> None:
        """Send each worker its message (new arrays, settings) and wait until all have taken them."""
        for conn, message in zip(self._conns, messages):
            conn.send(message)
        self.params[0] = SYNC
        self._wake(len(messages), timeout)

    def run(self, code: int, count: int, local) -> np.ndarray:
        """Phase `code` on workers 0..count-1 (ranges 1..count), with `local()` (range 0) run here in the
        meantime; the params must be posted first. Returns the workers' answers (count, RESULTS - 1)."""
        self.params[0] = code
        for w in range(count):
            self._go[w].release()
        try:
            local()
        finally:
            try:
                self._collect(count, None)
            except BaseException:  # interrupted while waiting (Ctrl-C): the semaphores' counts are unknown now
                self.close()
                raise
        return self.results[:count, 1:]

    def _wake(self, count: int, timeout: float | None) -> None:
        for w in range(count):
            self._go[w].release()
        self._collect(count, timeout)

    def _collect(self, count: int, timeout: float | None) -> None:
        waited = 0.0
        got = 0
        while got < count:
            if self._done.acquire(timeout=WAIT_SLICE_S):
                got += 1
                continue
            waited += WAIT_SLICE_S
            dead = [w for w in range(count) if not self._procs[w].is_alive()]
            if dead or (timeout is not None and waited >= timeout):
                w = dead[0] if dead else 0
                why = f"exited with code {self._procs[w].exitcode}" if dead else f"did not answer in {timeout:.0f} s"
                self.close()
                raise PoolError(f"AI worker {w + 1} {why}")
        failed = np.flatnonzero(self.results[:count, 0] < 0)
        if failed.size:
            w = int(failed[0])
            line = self._conns[w].recv() if self._conns[w].poll(5.0) else "no message"
            raise PoolError(f"AI worker {w + 1}: {line}")

    def close(self) -> None:
        self._finalizer()

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive

    @property
    def healthy(self) -> bool:
        """Open, and every worker process still running (one that exited is only found by the next wait)."""
        return not self.closed and all(proc.is_alive() for proc in self._procs)

    @staticmethod
    def _shutdown(procs, go, params, conns, control, results) -> None:
        if not control.closed:
            params[0] = STOP
            for proc, sem in zip(procs, go):
                if proc.is_alive():
                    sem.release()
        for proc in procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5.0)
        for conn in conns:
            conn.close()
        control.close()
        results.close()
