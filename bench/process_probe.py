"""Probe (issue 20): the AI's kind of numpy kernel over n agents, in P spawned processes on shared memory,
3 round trips a step (semaphores), against the same kernel whole in one process.
Run: python -m bench.process_probe 10000,100000,1000000 1,2,4,8,12,16 (output: docs/bench/process_probe_h200.txt)"""
import sys, time, numpy as np, multiprocessing as mp
from multiprocessing import shared_memory
NAMES = "x z vx vz tx tz a b".split()

def kernel(A, s):
    x, z, vx, vz, tx, tz = (A[k][s] for k in ("x", "z", "vx", "vz", "tx", "tz"))
    dx = tx - x; dz = tz - z
    d = np.sqrt(dx * dx + dz * dz)
    speed = 1.3 * np.minimum(np.maximum(d * 2.0, 0.0), 1.0)
    scale = speed / np.maximum(d, 1e-9)
    cx, cz = dx * scale - vx, dz * scale - vz
    limit = np.minimum(1.0, 0.2 / np.maximum(np.sqrt(cx * cx + cz * cz), 1e-12))
    vx += cx * limit; vz += cz * limit
    x += vx * 0.016; z += vz * 0.016
    sp = np.sqrt(vx * vx + vz * vz)
    w = np.minimum(sp / 1.2, 1.0)
    A["a"][s] = w; A["b"][s] = 1 - w

def worker(name, n, lo, hi, go, done):
    from crowd.allocator import keep_freed_memory; keep_freed_memory()
    shm = shared_memory.SharedMemory(name=name)
    big = np.ndarray((len(NAMES), n), np.float64, shm.buf)
    A = dict(zip(NAMES, big))
    s = slice(lo, hi)
    while True:
        go.acquire()
        if big[0, 0] < -1e30: break
        kernel(A, s)
        done.release()
    del A, big; shm.close()

if __name__ == "__main__":
    from crowd.allocator import keep_freed_memory; keep_freed_memory()
    ctx = mp.get_context("spawn")
    for n in [int(v) for v in sys.argv[1].split(",")]:
        shm = shared_memory.SharedMemory(create=True, size=len(NAMES) * n * 8)
        big = np.ndarray((len(NAMES), n), np.float64, shm.buf); big[:] = np.random.default_rng(0).random(big.shape)
        A = dict(zip(NAMES, big))
        k = 60
        kernel(A, slice(None)); t0 = time.perf_counter()
        for _ in range(k):
            for _ in range(3): kernel(A, slice(None))
        print(n, "one process, 3 kernels", round((time.perf_counter() - t0) / k * 1e3, 3), "ms", flush=True)
        for P in [int(v) for v in sys.argv[2].split(",")]:
            done = ctx.Semaphore(0); gos = [ctx.Semaphore(0) for _ in range(P)]
            ps = [ctx.Process(target=worker, args=(shm.name, n, w * n // P, (w + 1) * n // P, gos[w], done)) for w in range(P)]
            for p in ps: p.start()
            def trip():
                for g in gos: g.release()
                for _ in range(P): done.acquire()
            for _ in range(10): trip()
            ts = []
            for _ in range(k):
                t0 = time.perf_counter()
                for _ in range(3): trip()
                ts.append(time.perf_counter() - t0)
            # empty round trips: the cost of the sync alone
            big0 = big[0, 0]
            t0 = time.perf_counter()
            print(n, "P", P, "3 trips median", round(float(np.median(ts)) * 1e3, 3), "ms", flush=True)
            big[0, 0] = -1e31
            for g in gos: g.release()
            for p in ps: p.join()
            big[0, 0] = big0
        del A, big; shm.close(); shm.unlink()
