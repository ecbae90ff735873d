"""What every benchmark shares: the machine record, a fair clock, and the JSON output."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
FIGURES = ROOT / "figures"


def machine() -> dict:
    """Machine, backend and commit, printed and stored with every result."""
    import taichi as ti

    from tissue import backend

    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
        commit += "+dirty" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    be = backend.current()
    return {"cpu": cpu, "cores": os.cpu_count(), "arch": be.arch, "precision": be.precision,
            "taichi": ti.__version__, "commit": commit,
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


def print_machine(info: dict) -> None:
    print(f"# {info['cpu']} ({info['cores']} cores) · arch {info['arch']} · {info['precision']} · "
          f"taichi {info['taichi']} · commit {info['commit']} · {info['date']}")


def start_on_cpu() -> dict:
    """Taichi on the CPU in float64, and the machine (machine()), printed: the start of a benchmark
    that steps in its own process."""
    from tissue import backend

    backend.init(arch="cpu", precision="f64")
    info = machine()
    print_machine(info)
    return info


def time_steps(step, steps: int, warmup: int = 3) -> dict:
    """Median and spread of the wall time of `step()` (after ti.sync), warm-up excluded."""
    import taichi as ti

    for _ in range(warmup):
        step()
    samples = []
    for _ in range(steps):
        ti.sync()
        start = time.perf_counter()
        step()
        ti.sync()
        samples.append(time.perf_counter() - start)
    s = np.array(samples) * 1e3
    return {"median_ms": float(np.median(s)), "min_ms": float(s.min()), "p90_ms": float(np.percentile(s, 90)),
            "samples": len(s)}


def write_results(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2))
    print(f"# wrote {path.relative_to(ROOT)}")
    return path


def run_child(checkout: Path, child: str, args=(), env=None, required: bool = True) -> dict:
    """Run the script `child` (python -c) with `checkout` on PYTHONPATH and in its folder, `args` as
    its argv and `env` added to the environment; return the JSON of its line "RESULT {...}" ({} where
    none and not `required`), or raise with the end of its stderr where it failed."""
    done = subprocess.run([sys.executable, "-c", child, *map(str, args)], cwd=checkout, capture_output=True,
                          text=True, env={**os.environ, **(env or {}), "PYTHONPATH": str(checkout)})
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or (required and not lines):
        raise RuntimeError(f"{checkout}: {done.stderr.strip()[-2000:]}")
    return json.loads(lines[0][len("RESULT "):]) if lines else {}


def alternate_with_commit(other: str, rounds: int, measure, describe, prefix: str) -> tuple[str, dict]:
    """`measure(checkout)` on this checkout and on commit `other` (checked out in a temporary git
    worktree), alternately for `rounds` rounds (this one first in even rounds, the machine being
    shared), printing `describe(result)` after each. Returns other's short hash and the results,
    {"this": [...], "other": [...]} in round order."""
    import tempfile

    other = subprocess.run(["git", "rev-parse", "--short", other], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.strip()
    runs = {"this": [], "other": []}
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        worktree = Path(tmp) / "other"
        subprocess.run(["git", "worktree", "add", "--detach", str(worktree), other], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            for r in range(rounds):
                order = (("this", ROOT), ("other", worktree))
                for name, checkout in order if r % 2 == 0 else order[::-1]:
                    started = time.perf_counter()
                    runs[name].append(measure(checkout))
                    print(f"round {r + 1} {name:>5}: {time.perf_counter() - started:5.1f} s  "
                          + describe(runs[name][-1]), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=ROOT, capture_output=True)
    return other, runs
