#!/usr/bin/env bash
# GPU: lanes.sh's plans in a process session of their own, which outlives the device's calls, so that no step is
# cut at a call's end and started again in the next (the device kills what a call leaves running, except a new
# process session). A training that spans calls otherwise pays its start again (frames onto the GPU, compiling:
# 45-70 s at 384 a class) and loses the epoch it was in.
#   bash scripts/gpu/detached.sh PLAN_A PLAN_B+PLAN_C     (lanes.sh's arguments; the same command in every call)
# A call starts the plans unless they run already or have ended, then waits until they end or its BUDGET is spent
# (default 560), copying their lanes' queue.log and tarballs into $OUT/laneN as they grow, with the run's own log
# (detached.log). Back-to-back calls keep the machine: the run goes on between them. RUN_BUDGET (seconds,
# default 1700: a session's device time) bounds the whole run, as BUDGET bounds a call of lanes.sh: each step
# gets what is left of it. The run's state is QUEUE_STATE (default /tmp/queue): remove it to run the plans afresh.
# Change nothing in the checkout between the calls of a run: each call copies it to the machine again, and the run
# reads its scripts (bash reads a script as it goes) and imports its modules from that copy.
# Exit status: 0 while the run goes on or when it ended with 0, 2 for a bad plan (nothing started), else the
# run's (lanes.sh's) exit status.
set -uo pipefail
[ $# -ge 1 ] || { echo "usage: bash scripts/gpu/detached.sh PLAN[+PLAN...] [PLAN[+PLAN...]...]" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
state=${QUEUE_STATE:-/tmp/queue}
out=${OUT:-/tmp/out}
budget=${BUDGET:-560}
run_out=$state/detached-out pidfile=$state/detached.pid rcfile=$state/detached.rc runlog=$state/detached.log
lock=$state/detached.lock
mkdir -p "$state" "$out"
t0=$SECONDS

# The run holds a lock on $lock for as long as any of its processes lives (they inherit it): a process id could
# outlive its run or be reused, the lock cannot. A run with an exit status has ended, whatever still holds it.
alive() { [ ! -f "$rcfile" ] && ! flock -n "$lock" true 2> /dev/null; }
# copy: what the run has brought so far into this call's $OUT (each file through a temporary name, so a call cut
# off mid-copy still returns the last whole one)
copy() {
  local f rel
  for f in "$run_out"/lane*/*; do
    [ -f "$f" ] || continue
    [[ "$f" == *.tmp ]] && continue          # a tarball being packed: its last whole one is beside it
    rel=${f#"$run_out"/}
    mkdir -p "$out/$(dirname "$rel")"
    cp -f "$f" "$out/$rel.tmp" 2>/dev/null && mv -f "$out/$rel.tmp" "$out/$rel"
  done
  [ -f "$runlog" ] && cp -f "$runlog" "$out/detached.log"
}

if alive; then
  echo "detached: the plans run since an earlier call (pid $(cat "$pidfile" 2> /dev/null)); waiting"
elif [ -f "$rcfile" ]; then
  echo "detached: the plans ended in an earlier call (exit $(cat "$rcfile"))"
else
  for lane in "$@"; do         # a bad plan is said here, not in a log nobody reads
    why=$(bash "$here/queue.sh" --check ${lane//+/ } 2>&1) || { echo "detached: $why: nothing started" >&2; exit 2; }
  done
  mkdir -p "$run_out"
  [ -f "$pidfile" ] && echo "detached: the last run stopped without an exit status; its queues go on from their state"
  rm -f "$pidfile"
  # setsid: a new process session, which the device leaves running when this call returns; fd 9 holds the lock
  # (waited for: a call's `alive` holds it for an instant)
  setsid bash -c 'exec 9> "$1"; flock -w 10 9 || exit 0; echo $$ > "$2"; rcfile=$3 runlog=$4; shift 4
                  "$@" >> "$runlog" 2>&1; echo $? > "$rcfile.tmp"; mv -f "$rcfile.tmp" "$rcfile"' \
    _ "$lock" "$pidfile" "$rcfile" "$runlog" env BUDGET="${RUN_BUDGET:-1700}" QUEUE_STATE="$state" \
    OUT="$run_out" bash "$here/lanes.sh" "$@" < /dev/null > /dev/null 2>&1 &
  for _ in $(seq 50); do { alive || [ -f "$rcfile" ]; } && break; sleep 0.1; done
  echo "detached: started the plans (pid $(cat "$pidfile" 2> /dev/null), RUN_BUDGET ${RUN_BUDGET:-1700} s)"
fi

last_copy=$SECONDS
while alive && [ $((SECONDS - t0)) -lt $((budget - 15)) ]; do
  sleep 2
  if [ $((SECONDS - last_copy)) -ge 30 ]; then copy; last_copy=$SECONDS; fi
done
copy
if alive; then
  echo "detached: still running after $((SECONDS - t0)) s of this call: call again"
  tail -3 "$runlog" 2>/dev/null | sed 's/^/  /'
  for log in "$run_out"/lane*/queue.log; do [ -f "$log" ] && grep '^== ' "$log" | tail -2 | sed 's/^/  /'; done
  exit 0
fi
if [ ! -f "$rcfile" ]; then
  echo "detached: the run's processes are gone without an exit status (killed?): call again to go on from its state"
  exit 1
fi
rc=$(cat "$rcfile")
echo "detached: the plans ended (exit $rc)"
tail -20 "$runlog" 2>/dev/null
exit "$rc"
