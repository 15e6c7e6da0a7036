"""A 2-job sweep on Hydra's joblib launcher against the same two jobs one after another
(Hydra's basic launcher), measured back to back in one call (issue 19 item 2: at most 0.65).

    .venv/bin/python scripts/bench_launchers.py [--repeats 2] [--workloads ball humanoid] [--json out.json]

Each repeat runs both variants, in alternating order (basic then joblib, then joblib then basic),
so that a change in the machine's load over the call weighs on both alike. Reported per variant:
wall time, and the CPU time its processes got (so cpu/wall is the cores it had on average); the
load average before and after says how busy the machine was with other work. A control without
hvc comes first: the same fixed pure-Python work in two processes at once against one after
another, the best ratio any launcher can reach on the machine as loaded at that time. Sweep dirs
go to a temp dir and are removed.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WORKLOADS = {
    # the rolling ball: 8 envs in the main process and one torch thread, so one core per job
    # whatever the launcher; training includes learner updates
    "ball": ["body=rolling_ball", "controller=end_to_end", "stage=train", "total_steps=20000", "seed=0,1"],
    # the humanoid with fragments, num_envs=auto: one after another each job takes every core
    # (2 envs here), under joblib each takes cores // 2
    "humanoid": ["stage=rollout", "total_steps=1500", "seed=0,1"],
}


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _burn(n: int) -> int:
    total = 0
    for i in range(n):
        total += i * i % 7
    return total


def run_control(parallel: bool, n: int = 60_000_000) -> tuple[float, float]:
    """Wall and CPU seconds of two processes' fixed work, at once or one after another."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    cpu, start = _children_cpu(), time.perf_counter()
    if parallel:
        procs = [ctx.Process(target=_burn, args=(n,)) for _ in range(2)]
        for p in procs:
            p.start()
        for p in procs:
            p.join()
    else:
        for _ in range(2):
            p = ctx.Process(target=_burn, args=(n,))
            p.start()
            p.join()
    return time.perf_counter() - start, _children_cpu() - cpu


def run_sweep(launcher: str, overrides: list[str], sweep_dir: Path) -> tuple[float, float]:
    """Wall and CPU seconds of `hvc-run -m <overrides> hydra/launcher=<launcher>`; both jobs must finish."""
    cmd = [sys.executable, "-m", "hvc.cli", "-m", *overrides, f"hydra/launcher={launcher}",
           f"hydra.sweep.dir={sweep_dir}"]
    cpu, start = _children_cpu(), time.perf_counter()
    result = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall, cpu = time.perf_counter() - start, _children_cpu() - cpu
    jobs = [p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")]
    if result.returncode != 0 or len(jobs) != 2 or not all((j / "summary.json").exists() for j in jobs):
        raise SystemExit(f"{' '.join(cmd)} failed (rc {result.returncode}):\n{result.stderr[-3000:]}")
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--workloads", nargs="+", default=["control", *WORKLOADS], choices=["control", *WORKLOADS])
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    record = {"cores": len(os.sched_getaffinity(0)), "load_before": os.getloadavg(), "workloads": {}}
    print(f"cores {record['cores']}, load average {record['load_before'][0]:.2f} (1 min) before")
    with tempfile.TemporaryDirectory(prefix="hvc-bench-launchers-") as tmp:
        for name in args.workloads:
            runs = {"basic": [], "joblib": []}
            for repeat in range(args.repeats):
                order = ("basic", "joblib") if repeat % 2 == 0 else ("joblib", "basic")
                for launcher in order:
                    if name == "control":  # "joblib" stands for two at once here
                        wall, cpu = run_control(parallel=launcher == "joblib")
                    else:
                        wall, cpu = run_sweep(launcher, WORKLOADS[name], Path(tmp) / f"{name}_{launcher}_{repeat}")
                    runs[launcher].append({"wall_s": round(wall, 2), "cpu_s": round(cpu, 2)})
                    label = {"basic": "serial", "joblib": "at once"}[launcher] if name == "control" else launcher
                    print(f"{name:9s} {label:7s} repeat {repeat}: {wall:6.1f} s wall, {cpu:6.1f} s CPU "
                          f"({cpu / wall:.2f} cores)", flush=True)
            basic = sum(r["wall_s"] for r in runs["basic"])
            joblib = sum(r["wall_s"] for r in runs["joblib"])
            ratios = [j["wall_s"] / b["wall_s"] for j, b in zip(runs["joblib"], runs["basic"])]
            record["workloads"][name] = {"overrides": WORKLOADS.get(name, "two processes of pure-Python work"), "runs": runs, "ratio": round(joblib / basic, 3),
                                         "ratio_per_repeat": [round(r, 3) for r in ratios]}
            print(f"{name:9s} joblib / one after another: {joblib / basic:.3f} "
                  f"(per repeat {', '.join(f'{r:.3f}' for r in ratios)}; target <= 0.65)", flush=True)
    record["load_after"] = os.getloadavg()
    print(f"load average {record['load_after'][0]:.2f} (1 min) after")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
