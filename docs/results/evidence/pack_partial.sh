#!/usr/bin/env bash
# Before a session's end: packs every job of the given jobs files that has started and not
# finished (a checkpoint, or for stage=lowlevel an experts/ dir, and no summary.json) into
# docs/results/evidence/partial/<job name>.tar.gz (python -m hvc.io.pack: no replay buffers),
# and deletes the packs of high-level jobs that have finished since (their exported runs hold
# the results; a finished stage=lowlevel job stays packed: its library is other jobs' input);
# commit the dir afterwards. A new
# machine's queue.sh unpacks them with PARTIAL=docs/results/evidence/partial.
#   docs/results/evidence/pack_partial.sh docs/results/evidence/vision.jobs docs/results/evidence/fig6.jobs ...
set -uo pipefail
out=${OUT:-docs/results/evidence/partial}
python=${PYTHON:-.venv/bin/python}
mkdir -p "$out"
for jobs_file in "$@"; do
  while read -r dir _; do
    [[ -z $dir || $dir == \#* ]] && continue
    name=${dir##*/}
    if [[ -f $dir/summary.json && ! -d $dir/experts ]]; then
      rm -f "$out/$name.tar.gz"
    elif [[ -f $dir/checkpoint.pt || -d $dir/experts ]]; then  # a finished expert run too: its library is an input
      "$python" -m hvc.io.pack "$dir" "$out/$name.tar.gz"
    fi
  done < "$jobs_file"
done
