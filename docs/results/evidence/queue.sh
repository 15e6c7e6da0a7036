#!/usr/bin/env bash
# Runs the evidence jobs listed in a jobs file ("<run dir> <hvc-run overrides...>" per line),
# WORKERS at a time. A job whose dir has summary.json is done; one with checkpoint.pt (or, for
# stage=lowlevel, experts/) is continued with resume=<dir>; otherwise it starts in <dir>. Each job holds flock on
# <dir>.lock, so two queues never run the same job (the lock dies with its process). A queue runs the
# jobs its file held when it started.
# On a new machine: DONE=<dir> skips jobs exported there (<DONE>/<job name>/summary.json, as
# analysis/export_runs.py writes them); PARTIAL=<dir> first unpacks <PARTIAL>/<job name>.tar.gz
# (python -m hvc.io.pack) of a job this machine has no dir for, so it resumes, and of the run a job's
# branch_from= names, so a branch not yet started has its source. Such a branch waits while a queue
# runs its source (its lock held), and is skipped, said so, if the source has neither finished nor a queue
# running it: a source still waiting its turn in a queue's list counts as neither, so list a branch where
# its source will have started (after it on the same worker, or in a queue started after the source's).
#   nohup docs/results/evidence/queue.sh docs/results/evidence/<figure>.jobs > outputs/evidence/<figure>.log 2>&1 &
set -uo pipefail
jobs_file=$1
workers=${WORKERS:-2}
HVC=${HVC:-.venv/bin/hvc-run}

unpack() {  # <dir>: from $PARTIAL/<its name>.tar.gz, when this machine has no such dir
  local dir=$1 name=${1##*/}
  if [[ ! -e $dir && -n ${PARTIAL:-} && -f $PARTIAL/$name.tar.gz ]]; then
    local tmp  # unpacked aside, then moved in whole: a failed or concurrent unpack leaves no half dir
    mkdir -p "$(dirname "$dir")"
    tmp=$(mktemp -d "$(dirname "$dir")/.unpack.XXXXXX")
    if tar xzf "$PARTIAL/$name.tar.gz" -C "$tmp" && [[ -d $tmp/$name ]]; then
      mv -T "$tmp/$name" "$dir" 2>/dev/null || echo "$(date -Is) $dir appeared while unpacking; kept it"
    else
      echo "$(date -Is) could not unpack $PARTIAL/$name.tar.gz (no $name/ inside?); $dir starts fresh"
    fi
    rm -rf "$tmp"
  fi
}

running() {  # <run dir>: whether a queue holds its lock
  flock -n -E 75 "$1.lock" true 2>/dev/null
  (( $? == 75 ))
}

source_finished() {  # <run dir>: waits while a queue runs it; false (and says so) if it does not finish
  local src=$1 looks=0
  until [[ -f $src/summary.json ]]; do
    # looked at twice, a wait apart: a queue starting the source beside this one may not hold it yet.
    # A source still waiting in some queue's list is not seen: list a branch where its source has started
    if running "$src"; then
      looks=0
    elif (( looks++ >= 1 )); then
      echo "$(date -Is) branch of $src skipped: it has not finished and no queue runs it"
      return 1
    fi
    sleep "${WAIT_SECONDS:-60}"
  done
}

run_job() {
  local dir=$1; shift
  local name=${dir##*/} arg
  if [[ -f $dir/summary.json || ( -n ${DONE:-} && -f $DONE/$name/summary.json ) ]]; then return 0; fi
  unpack "$dir"
  for arg in "$@"; do  # a branch not yet started: its source unpacked, and finished first
    if [[ $arg == branch_from=* && ! -e $dir ]]; then
      unpack "${arg#branch_from=}"
      source_finished "${arg#branch_from=}" || return 0
    fi
  done
  local start=hydra.run.dir rc
  [[ -f $dir/checkpoint.pt || -d $dir/experts ]] && start=resume
  # a few seconds' wait, not -n: a branch's look at this lock (running) holds it for an instant
  flock -w "${LOCK_WAIT:-5}" -E 75 "$dir.lock" "$HVC" "$start=$dir" "$@"
  rc=$?  # read before the echo: its $(date) would set $? to 0
  if (( rc == 75 )); then
    echo "$(date -Is) job $dir skipped: another queue runs it"
  else
    echo "$(date -Is) job $dir exit $rc"
  fi
}

worker() {  # <index>: every workers-th job of the list, from the index-th
  local me=$1 i=0 line dir args
  for line in "${job_lines[@]}"; do
    read -r dir args <<< "$line"
    [[ -z ${dir:-} || $dir == \#* ]] && continue
    if (( i++ % workers == me )); then
      # shellcheck disable=SC2086
      mkdir -p "$(dirname "$dir")"
      run_job "$dir" $args >> "$dir.out" 2>&1 < /dev/null || true
      tail -1 "$dir.out"
    fi
  done
}

main() {
  [[ -f $jobs_file ]] || { echo "queue.sh: no jobs file $jobs_file" >&2; return 2; }
  # the jobs as the file holds them now: an edit to it while the queue runs changes nothing here
  mapfile -t job_lines < "$jobs_file"
  for ((w = 0; w < workers; w++)); do worker "$w" & done
  wait
}

# bash reads a script as it runs it: with everything in functions and the last line read
# before main starts, an edit to this file cannot reach a queue already running
main; exit
