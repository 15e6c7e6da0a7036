"""docs/results/evidence/queue.sh, the jobs-file runner the evidence runs go through: what it
starts, resumes, skips and logs, driven with a fake hvc-run that records its arguments."""
import os
import shutil
import subprocess
import tarfile
import textwrap
from pathlib import Path

import pytest

QUEUE = Path(__file__).resolve().parents[1] / "docs/results/evidence/queue.sh"

pytestmark = pytest.mark.skipif(not (shutil.which("bash") and shutil.which("flock")), reason="needs bash and flock")


def fake_hvc(tmp_path: Path, exit_code: int = 0) -> Path:
    """An hvc-run that appends its arguments to calls.txt and exits with exit_code."""
    script = tmp_path / "fake-hvc"
    script.write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        echo "$*" >> {tmp_path}/calls.txt
        exit {exit_code}
        """))
    script.chmod(0o755)
    return script


def run_queue(tmp_path: Path, jobs: str, hvc: Path, **env: str) -> tuple[list[str], str]:
    jobs_file = tmp_path / "x.jobs"
    jobs_file.write_text(jobs)
    result = subprocess.run(["bash", str(QUEUE), str(jobs_file)], cwd=tmp_path, capture_output=True, text=True,
                            env={**os.environ, "HVC": str(hvc), "WORKERS": "1", "LOCK_WAIT": "1", **env}, timeout=60)
    assert result.returncode == 0, result.stderr
    calls = tmp_path / "calls.txt"
    return (calls.read_text().splitlines() if calls.exists() else []), result.stdout


def test_starts_new_jobs_resumes_started_ones_and_skips_finished(tmp_path):
    (tmp_path / "runs/started").mkdir(parents=True)
    (tmp_path / "runs/started/checkpoint.pt").write_bytes(b"")
    (tmp_path / "runs/finished").mkdir()
    (tmp_path / "runs/finished/summary.json").write_text("{}")
    calls, _ = run_queue(tmp_path, "# a comment\nruns/new seed=0\n\nruns/started seed=1\nruns/finished seed=2\n",
                         fake_hvc(tmp_path))
    assert calls == ["hydra.run.dir=runs/new seed=0", "resume=runs/started seed=1"]


def test_logs_the_jobs_own_exit_code(tmp_path):
    # the log line's $(date) once reset $? so every job was logged "exit 0"
    _, out = run_queue(tmp_path, "runs/a seed=0\n", fake_hvc(tmp_path, exit_code=3))
    assert "job runs/a exit 3" in (tmp_path / "runs/a.out").read_text() + out


def test_a_job_another_queue_holds_is_skipped_not_run(tmp_path):
    (tmp_path / "runs").mkdir()
    holder = subprocess.Popen(["flock", str(tmp_path / "runs/a.lock"), "sleep", "30"])
    try:
        for _ in range(100):  # until the holder has the lock
            if subprocess.run(["flock", "-n", str(tmp_path / "runs/a.lock"), "true"]).returncode:
                break
        calls, _ = run_queue(tmp_path, "runs/a seed=0\nruns/b seed=1\n", fake_hvc(tmp_path))
    finally:
        holder.kill()
    assert calls == ["hydra.run.dir=runs/b seed=1"]
    assert "job runs/a skipped: another queue runs it" in (tmp_path / "runs/a.out").read_text()


def test_done_and_partial(tmp_path):
    (tmp_path / "exported/done").mkdir(parents=True)
    (tmp_path / "exported/done/summary.json").write_text("{}")
    packed = tmp_path / "staging/packed"
    packed.mkdir(parents=True)
    (packed / "checkpoint.pt").write_bytes(b"state")
    (tmp_path / "partial").mkdir()
    with tarfile.open(tmp_path / "partial/packed.tar.gz", "w:gz") as tar:
        tar.add(packed, arcname="packed")
    calls, _ = run_queue(tmp_path, "runs/done seed=0\nruns/packed seed=1\n", fake_hvc(tmp_path),
                         DONE="exported", PARTIAL="partial")
    assert calls == ["resume=runs/packed seed=1"]  # unpacked, then resumed; the exported job not rerun
    assert (tmp_path / "runs/packed/checkpoint.pt").read_bytes() == b"state"


def test_a_branch_not_yet_started_has_its_source_unpacked(tmp_path):
    """A job `branch_from=<run>` on a new machine: the source run comes out of PARTIAL first;
    once the branch has its own dir, the source is not needed (nor unpacked) again."""
    source = tmp_path / "staging/trunk"
    (source / "experts/0_run").mkdir(parents=True)
    (source / "experts/0_run/checkpoint.pt").write_bytes(b"trunk")
    (source / "summary.json").write_text("{}")  # finished: a branch waits for its source to finish
    (tmp_path / "partial").mkdir()
    with tarfile.open(tmp_path / "partial/trunk.tar.gz", "w:gz") as tar:
        tar.add(source, arcname="trunk")
    (tmp_path / "runs/started/experts").mkdir(parents=True)
    calls, _ = run_queue(tmp_path, "runs/branch branch_from=src/trunk seed=0\nruns/started branch_from=other/trunk\n",
                         fake_hvc(tmp_path), PARTIAL="partial")
    assert calls == ["hydra.run.dir=runs/branch branch_from=src/trunk seed=0", "resume=runs/started branch_from=other/trunk"]
    assert (tmp_path / "src/trunk/experts/0_run/checkpoint.pt").read_bytes() == b"trunk"
    assert not (tmp_path / "other").exists()


def test_edits_to_the_jobs_file_or_the_script_do_not_reach_a_running_queue(tmp_path):
    """A queue runs the jobs its file held when it started, and an in-place edit of queue.sh while
    it runs (bash reads a script as it goes: one once broke a running queue's last line) leaves it
    to finish as it started. The first job's hvc-run makes both edits."""
    queue = tmp_path / "queue.sh"
    queue.write_bytes(QUEUE.read_bytes())
    jobs_file = tmp_path / "x.jobs"
    jobs_file.write_text("runs/a seed=0\nruns/b seed=1\n")
    script = tmp_path / "fake-hvc"
    # the same inode rewritten: what an editor or `cat >` does; where the old script's next line
    # stood, the new text says `exit 9`
    script.write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        echo "$*" >> {tmp_path}/calls.txt
        if [[ $* == *runs/a* ]]; then
          echo "runs/c seed=2" >> {jobs_file}
          size=$(stat -c %s {queue})
          {{ head -c "$size" /dev/zero | tr '\\0' '#'; printf '\\nexit 9\\n'; }} > {queue}.new
          cat {queue}.new > {queue}
        fi
        """))
    script.chmod(0o755)
    result = subprocess.run(["bash", str(queue), str(jobs_file)], cwd=tmp_path, capture_output=True, text=True,
                            env={**os.environ, "HVC": str(script), "WORKERS": "1"}, timeout=60)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "calls.txt").read_text().splitlines() == ["hydra.run.dir=runs/a seed=0",
                                                                  "hydra.run.dir=runs/b seed=1"]


def test_a_branch_waits_for_its_source_to_finish_or_is_skipped_without_one(tmp_path):
    """Two workers: the branch's worker waits while the other runs its source, then branches from
    the finished run; a branch whose source has neither finished nor a queue is not run."""
    script = tmp_path / "fake-hvc"
    script.write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        echo "$*" >> {tmp_path}/calls.txt
        if [[ $* == *runs/trunk* && $* != *branch_from* ]]; then
          sleep 2; mkdir -p runs/trunk; echo '{{}}' > runs/trunk/summary.json
        fi
        """))
    script.chmod(0o755)
    calls, _ = run_queue(tmp_path, "runs/trunk seed=0\nruns/branch branch_from=runs/trunk seed=1\n"
                                   "runs/orphan branch_from=runs/nowhere seed=2\n",
                         script, WORKERS="2", WAIT_SECONDS="1")
    assert calls == ["hydra.run.dir=runs/trunk seed=0", "hydra.run.dir=runs/branch branch_from=runs/trunk seed=1"]
    assert "branch of runs/nowhere skipped: it has not finished and no queue runs it" in \
        (tmp_path / "runs/orphan.out").read_text()
