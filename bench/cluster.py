"""Run benchmark cells as independent tasks on Dask's distributed scheduler.

Default: a LocalCluster of worker *processes* (2 workers × 1 thread: one cell per core, each worker
initialising its own Taichi backend), no dashboard, nothing reached over the network, so it runs
offline. `--scheduler tcp://host:port` sends the cells to a running cluster instead (its workers
need `tissue` installed; the `bench` package is uploaded to them).

A cell is a plain function of one JSON-like dict that returns a JSON-like dict. Exceptions of a
cell are caught by the scheduler and come back as an "error" entry of that cell only.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import zipfile
from contextlib import contextmanager
from pathlib import Path

BENCH = Path(__file__).resolve().parent


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:port); "
                                            "default: a LocalCluster on this machine")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    parser.add_argument("--arch", default=os.environ.get("TISSUE_ARCH", "cpu"),
                        help="Taichi arch of every cell: cpu (default), cuda, vulkan or auto")


@contextmanager
def client(args):
    from dask.distributed import Client, LocalCluster

    if args.scheduler:
        with Client(args.scheduler) as c:
            with tempfile.TemporaryDirectory() as tmp:   # ship this package to the workers
                archive = Path(tmp) / "bench.zip"
                with zipfile.ZipFile(archive, "w") as z:
                    for f in BENCH.glob("*.py"):
                        z.write(f, f"bench/{f.name}")
                c.upload_file(str(archive))
            yield c
        return
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, host="127.0.0.1") as cluster, Client(cluster) as c:
        yield c


def run_cells(c, function, cells: list[dict], label: str = "cells") -> list[dict]:
    """Submit every cell as its own task; return the results in the order of `cells`, printing
    the progress as they finish (about every twentieth of the sweep)."""
    from dask.distributed import as_completed

    start = time.perf_counter()
    futures = c.map(function, cells, pure=False)
    position = {future.key: i for i, future in enumerate(futures)}
    out: list[dict | None] = [None] * len(cells)
    every = max(1, len(cells) // 20)
    for done, future in enumerate(as_completed(futures), 1):
        i = position[future.key]
        try:
            out[i] = future.result()
        except Exception as e:  # a crash of one cell is that cell's result, not the sweep's end
            out[i] = {**cells[i], "error": f"{type(e).__name__}: {e}"}
        if done % every == 0 and done < len(cells):
            print(f"{label}: {done} of {len(cells)} tasks done, {time.perf_counter() - start:.0f} s", flush=True)
    print(f"{label}: {len(cells)} tasks in {time.perf_counter() - start:.1f} s", flush=True)
    return out


def worker_backend(arch: str, precision: str = "f64"):
    """Initialise Taichi in this worker process (one thread per worker: cells share no cores)."""
    from tissue import backend

    threads = {"cpu_max_num_threads": 1} if arch == "cpu" else {}
    return backend.init(arch, precision, **threads)


def worker_machine(arch: str, precision: str = "f64") -> dict:
    """bench.common.machine() as seen by a worker (its backend, not the client's)."""
    from bench.common import machine

    worker_backend(arch, precision)
    return machine()


def record(c, args) -> dict:
    info = c.submit(worker_machine, args.arch, pure=False).result()
    info["scheduler"] = args.scheduler or f"LocalCluster({args.workers} processes x 1 thread)"
    return info
