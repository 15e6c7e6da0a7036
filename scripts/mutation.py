#!/usr/bin/env python
"""Mutation testing of the modules that carry the paper's maths and the resume path (issue 21).

Each group mutates a few source files with mutmut and runs only that group's fast test
files against each mutant (mutmut further narrows to the tests that call the mutated
function). A group runs in its own scratch copy of the repository (`git archive HEAD`,
or the working tree with --worktree), so the checkout, its `mutants/` and anything
importing `hvc` from it are never touched. Results land in docs/results/mutation/:
`<group>.json` per group (commit, date, counts, every mutant's status, survivors' diffs)
and README.md, regenerated from all group files plus `equivalent.toml`, where surviving
mutants judged equivalent (cannot change behaviour) are listed by hand with a reason.

    make mutation                         # every group
    make mutation MUTATION_GROUPS=vtrace  # one group
    python scripts/mutation.py --list     # the groups
    python scripts/mutation.py --report   # README.md from the stored results only
    python scripts/mutation.py --count    # mutants per group, generated but not run (seconds)

Score = detected / (mutants - equivalent), detected = killed + timeout + segfault;
survivors and mutants no selected test reaches ("no tests") count as missed.
"""
from __future__ import annotations

import argparse
import datetime
import fnmatch
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tarfile
import io
import time
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "docs" / "results" / "mutation"
EQUIVALENT = RESULTS / "equivalent.toml"

# name: (files to mutate, fast test files, mutant-name globs or None for all mutants of the files)
GROUPS: dict[str, tuple[list[str], list[str], list[str] | None]] = {
    "reward": (["hvc/envs/tracking_reward.py"], ["tests/test_tracking_reward.py"], None),
    "vtrace": (["hvc/algorithms/vtrace.py"], ["tests/test_vtrace.py", "tests/test_agent.py", "tests/test_learner_state.py"],
               None),
    "retrace": (["hvc/algorithms/retrace.py"], ["tests/test_retrace.py", "tests/test_lowlevel.py"], None),
    # SVG(0) + Retrace at both levels: the low level's MLP learner and the high level's recurrent one
    "svg0": (["hvc/algorithms/svg0_retrace.py"],
             ["tests/test_lowlevel.py", "tests/test_agent.py", "tests/test_retrace.py", "tests/test_learner_state.py"],
             None),
    "wolpertinger": (["hvc/algorithms/wolpertinger.py", "hvc/controllers/query.py"],
                     ["tests/test_agent.py", "tests/test_controllers.py", "tests/test_learner_state.py"], None),
    "fragments_keys": (["hvc/controllers/fragments.py", "hvc/mocap/clip_sets.py"],
                       ["tests/test_controllers.py", "tests/test_clip_sets.py"], None),
    # checkpoint contents and their loading: the learners' and the replay's state, random streams
    # (the resume block of run_hl_training is left out: its mutants would rerun whole training runs)
    "resume": (["hvc/algorithms/replay.py", "hvc/runtime/hl_train.py", "hvc/algorithms/svg0_retrace.py",
                "hvc/algorithms/vtrace.py", "hvc/algorithms/wolpertinger.py", "hvc/io/checkpoint.py"],
               ["tests/test_learner_state.py", "tests/test_lowlevel.py"],
               ["hvc.runtime.hl_train.x_load_checkpoint*", "hvc.algorithms.*state_dict*",
                "hvc.io.checkpoint.x_*random_states*"]),
    "conversion": (["hvc/mocap/convert.py"], ["tests/test_mocap_convert.py"], None),
}
DETECTED = {"killed", "timeout", "segfault", "caught by type check"}


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()


def prepare(workdir: Path, worktree: bool, files: list[str], tests: list[str]) -> None:
    """A scratch copy of hvc/, conf/, tests/ and pyproject.toml with the group's mutmut config."""
    if workdir.exists():
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    parts = ["hvc", "conf", "tests", "pyproject.toml"]
    if worktree:
        for p in parts:
            src = REPO / p
            if src.is_dir():
                shutil.copytree(src, workdir / p, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                shutil.copy2(src, workdir / p)
    else:
        archive = subprocess.run(["git", "archive", "HEAD", *parts], cwd=REPO, check=True, capture_output=True).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(workdir, filter="data")
    for f in files:
        undecorate(workdir / f)
    pyproject = workdir / "pyproject.toml"
    text = pyproject.read_text()
    if "[tool.mutmut]" in text:
        raise SystemExit("pyproject.toml has its own [tool.mutmut]; this script writes the per-group one")
    cfg = {
        "source_paths": ["hvc"],
        "only_mutate": files,
        "pytest_add_cli_args_test_selection": tests,
        "pytest_add_cli_args": ["-p", "no:cacheprovider", "-q"],
        "also_copy": ["conf"],
        # torch is not fork-safe once its thread pools run: fork workers from a clean server
        "process_isolation": "forkserver",
    }
    lines = ["", "[tool.mutmut]"] + [f"{k} = {json.dumps(v)}" for k, v in cfg.items()]
    pyproject.write_text(text + "\n".join(lines) + "\n")


NEUTRAL_DECORATORS = ("torch.no_grad()",)


def undecorate(path: Path) -> int:
    """Moves a `@torch.no_grad()` decorator to a rebinding after the function (same behaviour):
    mutmut leaves decorated functions unmutated, and these are the Retrace and V-trace targets."""
    import ast

    lines = path.read_text().splitlines(keepends=True)
    found = []
    for node in ast.walk(ast.parse("".join(lines))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and len(node.decorator_list) == 1:
            dec = node.decorator_list[0]
            if ast.unparse(dec) in NEUTRAL_DECORATORS and dec.lineno == dec.end_lineno:
                found.append((dec.lineno, node.end_lineno, node.col_offset, node.name, ast.unparse(dec)))
    for dec_line, end, col, name, dec in sorted(found, reverse=True):
        lines.insert(end, f"{' ' * col}{name} = {dec}({name})\n")
        del lines[dec_line - 1]
    path.write_text("".join(lines))
    return len(found)


def child_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # hvc only from the mutants/ copy
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MUJOCO_GL=env.get("MUJOCO_GL", "egl"))
    shared = REPO.parent / "shared" / "mocap"
    if "HVC_SHARED_MOCAP" not in env and shared.is_dir():
        env["HVC_SHARED_MOCAP"] = str(shared)  # the scratch copy is not next to ../shared
    converted = REPO / "outputs" / "mocap" / "cmu_2019.h5"
    if "HVC_MOCAP_FILE" not in env and converted.is_file():
        env["HVC_MOCAP_FILE"] = str(converted)  # read only; spares a conversion per scratch copy
    return env


def mutmut(workdir: Path, *args: str, check: bool = True) -> str:
    cmd = [sys.executable, "-m", "mutmut", *args]
    out = subprocess.run(cmd, cwd=workdir, env=child_env(), capture_output=True, text=True)
    if check and out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")
    return out.stdout


def changed_lines(diff: str) -> str:
    """The -/+ lines of a unified diff (what a mutant changes), for matching equivalence notes."""
    return "\n".join(line.rstrip() for line in diff.splitlines()
                     if line[:1] in "+-" and not line.startswith(("+++", "---")))


def run_group(name: str, max_children: int, worktree: bool, workroot: Path) -> dict:
    files, tests, globs = GROUPS[name]
    present = [t for t in tests if (REPO / t).is_file()]
    missing = sorted(set(tests) - set(present))
    if missing:
        print(f"[{name}] test files not in the checkout, left out: {missing}")
    if not present:
        raise SystemExit(f"[{name}] none of its test files exist")
    workdir = workroot / name
    prepare(workdir, worktree, files, present)
    print(f"[{name}] mutmut over {files} with {present} in {workdir}", flush=True)
    start = time.monotonic()
    run_out = mutmut(workdir, "run", "--max-children", str(max_children), *(globs or []), check=False)
    duration = time.monotonic() - start
    (workdir / "mutmut-run.log").write_text(run_out)
    if "failed to collect stats" in run_out:  # the unmutated tests failed: no mutant result means anything
        raise RuntimeError(f"[{name}] the group's tests fail on the unmutated code in {workdir}; nothing recorded "
                           f"(see {workdir / 'mutmut-run.log'})")
    statuses = {}
    for line in mutmut(workdir, "results", "--all", "true").splitlines():
        m = re.match(r"\s+(\S+): (.+)$", line)
        if m and (globs is None or any(fnmatch.fnmatch(m.group(1), g) for g in globs)):
            statuses[m.group(1)] = m.group(2).strip()
    if not statuses:
        raise RuntimeError(f"[{name}] mutmut produced no results; see {workdir / 'mutmut-run.log'}:\n{run_out[-3000:]}")
    survivors = {}
    for mutant, status in sorted(statuses.items()):
        if status not in DETECTED:
            show = mutmut(workdir, "show", mutant)
            survivors[mutant] = {"status": status, "diff": show.split("\n", 1)[1].strip() if "\n" in show else show}
    dirty = bool(git("status", "--porcelain", "--", *files, *present)) if worktree else False
    return {
        "group": name, "files": files, "tests": present, "tests_missing": missing, "mutant_globs": globs,
        "commit": git("rev-parse", "HEAD"), "source": "worktree" if worktree else "HEAD",
        "uncommitted_changes": dirty, "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "duration_s": round(duration, 1), "max_children": max_children,
        "mutmut": _mutmut_version(),
        "python": platform.python_version(), "nice": os.nice(0),
        "command": " ".join(["python", "scripts/mutation.py", *sys.argv[1:]]),
        "statuses": statuses, "survivors": survivors,
    }


_GENERATE = ("from mutmut.__main__ import copy_src_dir, copy_also_copy_files, setup_source_paths, create_mutants\n"
             "copy_src_dir(); copy_also_copy_files(); setup_source_paths(); create_mutants(1)")


def count_group(name: str, worktree: bool, workroot: Path) -> int:
    """Mutants the group would run (generated with mutmut's own generator, no test run)."""
    files, tests, globs = GROUPS[name]
    workdir = workroot / f"{name}-count"
    prepare(workdir, worktree, files, tests)
    subprocess.run([sys.executable, "-c", _GENERATE], cwd=workdir, env=child_env(), check=True, capture_output=True)
    names = [m.group(1) for line in mutmut(workdir, "results", "--all", "true").splitlines()
             if (m := re.match(r"\s+(\S+): ", line))]
    shutil.rmtree(workdir)
    return sum(globs is None or any(fnmatch.fnmatch(n, g) for g in globs) for n in names)


def _mutmut_version() -> str:
    from importlib.metadata import version

    return f"mutmut {version('mutmut')}"


def load_equivalent() -> dict[str, dict]:
    if not EQUIVALENT.is_file():
        return {}
    return {m["name"]: m for m in tomllib.loads(EQUIVALENT.read_text()).get("mutant", [])}


def score(result: dict, equivalent: dict[str, dict]) -> dict:
    statuses = result["statuses"]
    equiv = [m for m, s in result["survivors"].items()
             if m in equivalent and changed_lines(s["diff"]) == changed_lines(equivalent[m]["change"])]
    counts: dict[str, int] = {}
    for s in statuses.values():
        counts[s] = counts.get(s, 0) + 1
    detected = sum(n for s, n in counts.items() if s in DETECTED)
    relevant = len(statuses) - len(equiv)
    return {"counts": counts, "detected": detected, "equivalent": equiv, "relevant": relevant,
            "score": detected / relevant if relevant else float("nan")}


def render() -> str:
    equivalent = load_equivalent()
    results = {n: json.loads((RESULTS / f"{n}.json").read_text()) for n in GROUPS if (RESULTS / f"{n}.json").is_file()}
    pending = [n for n in GROUPS if n not in results]
    out = ["# Mutation testing (issue 21)", "",
           "mutmut over the modules that carry the paper's maths and the resume path, each group against",
           "its own fast test files only. Generated by `scripts/mutation.py` from the `<group>.json` files",
           "here, the hand-written `equivalent.toml` (equivalent survivors and why) and `notes.md`;",
           "edit those, not this file.", "",
           "Command: `make mutation` (all groups; `MUTATION_GROUPS=\"vtrace retrace\"` for some), which runs",
           "`nice -n 19 .venv/bin/python scripts/mutation.py`. Not part of CI (too slow); run it before closing",
           "an issue that changes these modules. Target: at least 90% of non-equivalent mutants detected.", "",
           "Score = detected / (mutants - equivalent); detected = killed, timeout or segfault; survivors and",
           "mutants no selected test reaches (`no tests`) count as missed.", ""]
    notes = RESULTS / "notes.md"
    if notes.is_file():
        out += [notes.read_text().strip(), ""]
    if pending:
        out += [f"**Partial.** Groups not run yet (the full campaign is pending): {', '.join(pending)}.", ""]
    out += ["| group | mutated files | test files | commit | date | mutants | detected | missed | equivalent | score |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    scored = {}
    for name in GROUPS:
        files, tests, _ = GROUPS[name]
        if name not in results:
            out.append(f"| {name} | {', '.join(files)} | {', '.join(tests)} | | pending | | | | | |")
            continue
        r = results[name]
        s = scored[name] = score(r, equivalent)
        missed = s["relevant"] - s["detected"]
        out.append(f"| {name} | {', '.join(r['files'])} | {', '.join(r['tests'])} | {r['commit'][:10]}"
                   f"{' +wt' if r['uncommitted_changes'] else ''} | {r['date'][:10]} | {len(r['statuses'])} | "
                   f"{s['detected']} | {missed} | {len(s['equivalent'])} | {100 * s['score']:.1f}% |")
    if scored:
        det = sum(s["detected"] for s in scored.values())
        rel = sum(s["relevant"] for s in scored.values())
        out += ["", f"Over the groups run: {det} of {rel} non-equivalent mutants detected "
                f"({100 * det / rel:.1f}%){' (partial)' if pending else ''}."]
    for name, r in results.items():
        s = scored[name]
        out += ["", f"## {name}", "",
                f"`{r['command']}` on {r['source']} of {r['commit']}, {r['date']}, {r['duration_s']:.0f} s "
                f"with {r['max_children']} worker(s) at nice {r.get('nice', '?')}, {r['mutmut']}, Python {r['python']}. "
                f"Statuses: {', '.join(f'{k} {v}' for k, v in sorted(s['counts'].items()))}."]
        if r.get("mutant_globs"):
            out.append(f"Mutants restricted to {', '.join('`' + g + '`' for g in r['mutant_globs'])}.")
        if r.get("tests_missing"):
            out.append(f"Test files missing at the run, left out: {', '.join(r['tests_missing'])}.")
        for title, names in (("Equivalent survivors", s["equivalent"]),
                             ("Missed, not equivalent (tests to write)",
                              [m for m in r["survivors"] if m not in s["equivalent"]])):
            out += ["", f"### {title}: {len(names)}"]
            for m in names:
                sv = r["survivors"][m]
                out += ["", f"- `{m}` ({sv['status']})"
                        + (f": {equivalent[m]['reason']}" if m in s["equivalent"] else ""),
                        "", "  ```diff", *("  " + line for line in changed_lines(sv["diff"]).splitlines()), "  ```"]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("groups", nargs="*", help=f"groups to run (default all): {', '.join(GROUPS)}")
    parser.add_argument("--max-children", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--worktree", action="store_true", help="mutate the working tree, not HEAD")
    parser.add_argument("--workdir", type=Path, default=Path(os.environ.get("MUTATION_WORKDIR", "/tmp/hvc-mutation")))
    parser.add_argument("--list", action="store_true", help="print the groups and exit")
    parser.add_argument("--report", action="store_true", help="only regenerate README.md from stored results")
    parser.add_argument("--count", action="store_true", help="count each group's mutants without running tests")
    args = parser.parse_args(argv)
    if args.list:
        for name, (files, tests, globs) in GROUPS.items():
            print(f"{name}: {' '.join(files)} <- {' '.join(tests)}{'  [' + ' '.join(globs) + ']' if globs else ''}")
        return
    unknown = [g for g in args.groups if g not in GROUPS]
    if unknown:
        raise SystemExit(f"unknown groups {unknown}; choose from {list(GROUPS)}")
    if args.count:
        for name in args.groups or list(GROUPS):
            print(f"{name}: {count_group(name, args.worktree, args.workdir)} mutants", flush=True)
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    if not args.report:
        for name in args.groups or list(GROUPS):
            result = run_group(name, args.max_children, args.worktree, args.workdir)
            (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
            s = score(result, load_equivalent())
            print(f"[{name}] {s['detected']}/{s['relevant']} detected ({100 * s['score']:.1f}%), "
                  f"{len(result['survivors'])} survivors, {result['duration_s']:.0f} s", flush=True)
    (RESULTS / "README.md").write_text(render())
    print(f"wrote {RESULTS / 'README.md'}")


if __name__ == "__main__":
    main()
