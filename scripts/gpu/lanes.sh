#!/usr/bin/env bash
# GPU: several plans at once on one machine of several GPUs, each in its own lane of the machine's GPUs:
#   bash scripts/gpu/lanes.sh PLAN_A PLAN_B+PLAN_C     (the same command in every call)
# An argument is one lane: plans joined by + run one after another in that lane, as one queue (scripts/gpu/queue.sh
# PLAN PLAN...: a step two plans share, name and command, runs once; one name with two commands is refused). The
# GPUs are split evenly between the lanes (the first lanes get the remainder; with fewer GPUs than lanes, lanes
# share them round robin; with none, every lane runs with CUDA_VISIBLE_DEVICES empty, a CPU dry run), pinned with
# CUDA_VISIBLE_DEVICES, so each plan sizes its render workers and trainings by its own GPUs. Each lane's queue has
# its own state (QUEUE_STATE/laneN) and output ($OUT/laneN/queue.log and queue.tgz, with one or two lanes also
# queue-2.tgz for what queue.tgz cannot hold: at most three of the device's eight files a lane), resumable across
# calls. Lanes must not share a run folder: their plans' RUN paths differ.
# Exit status: 0 when every lane's queue returned 0 (steps that fail are recorded by the queue), 2 for a bad
# plan (before any lane starts), else 1.
set -uo pipefail
[ $# -ge 1 ] || { echo "usage: bash scripts/gpu/lanes.sh PLAN[+PLAN...] [PLAN[+PLAN...]...]" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
source "$here/gpus.sh"
state=${QUEUE_STATE:-/tmp/queue}
out=${OUT:-/tmp/out}
IFS=, read -r -a all <<< "$gpus"
nlanes=$#
mkdir -p "$state"

# Every lane's plans read by the queue before any lane starts.
i=0
for lane in "$@"; do
  i=$((i + 1))
  why=$(bash "$here/queue.sh" --check ${lane//+/ } 2>&1) || { echo "lanes: $why (lane $i): no lane started" >&2; exit 2; }
done

pids=()
for i in $(seq 1 "$nlanes"); do
  name=lane$i k=$((i - 1))
  # its GPUs: an even share, or one shared round robin when there are fewer GPUs than lanes
  if [ "${#all[@]}" -eq 0 ]; then
    mine=
  elif [ "${#all[@]}" -ge "$nlanes" ]; then
    share=$(( ${#all[@]} / nlanes )) extra=$(( ${#all[@]} % nlanes ))
    first=$(( k * share + (k < extra ? k : extra) )) count=$(( share + (k < extra ? 1 : 0) ))
    mine=$(IFS=,; echo "${all[*]:$first:$count}")
  else
    mine=${all[$(( k % ${#all[@]} ))]}
  fi
  echo "lanes: $name on GPUs ${mine:-(none)}: ${!i}"
  rm -f "$state/$name.rc"
  lane=${!i}
  ( CUDA_VISIBLE_DEVICES=$mine QUEUE_STATE="$state/$name" OUT="$out/$name" QUEUE_OVERFLOW=${QUEUE_OVERFLOW:-$((nlanes <= 2))} \
      bash "$here/queue.sh" ${lane//+/ } > /dev/null 2>&1; echo $? > "$state/$name.rc" ) &
  pids+=($!)
done
wait "${pids[@]}"
status=0
for i in $(seq 1 "$nlanes"); do
  rc=$(cat "$state/lane$i.rc" 2>/dev/null || echo 1)
  echo "lanes: lane$i's queue exit $rc; its last lines:"
  tail -4 "$out/lane$i/queue.log" 2>/dev/null | sed 's/^/  /'
  [ "$rc" = 0 ] || status=1
done
exit $status
