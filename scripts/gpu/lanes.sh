#!/usr/bin/env bash
# GPU: several plans at once on one machine of several GPUs, each in its own lane of the machine's GPUs:
#   bash scripts/gpu/lanes.sh PLAN_A PLAN_B+PLAN_C     (the same command in every call)
# An argument is one lane: plans joined by + run one after another in that lane (their steps, in order, as one
# queue). The GPUs are split evenly between the lanes (the first lanes get the remainder; with fewer GPUs than
# lanes, lanes share them round robin), pinned with CUDA_VISIBLE_DEVICES, so each plan sizes its render
# workers and trainings by its own GPUs. Each lane is a scripts/gpu/queue.sh with its own state
# (QUEUE_STATE/LANE) and output ($OUT/LANE/queue.log and queue.tgz: two of the device's eight files a lane),
# resumable across calls like one queue. A step name used twice in one lane runs once (the first).
# Exit status: 0 when every lane's queue returned 0 (steps that fail are recorded by the queue), else 1.
set -uo pipefail
[ $# -ge 1 ] || { echo "usage: bash scripts/gpu/lanes.sh PLAN[+PLAN...] [PLAN[+PLAN...]...]" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
source "$here/gpus.sh"
state=${QUEUE_STATE:-/tmp/queue}
out=${OUT:-/tmp/out}
IFS=, read -r -a all <<< "$gpus"
nlanes=$#
mkdir -p "$state"
pids=() i=0
for lane in "$@"; do
  name=lane$((i + 1))
  # this lane's plan: the steps of its plans in order, a step name that came before left out
  plan="$state/$name.plan"
  : > "$plan.new"
  for p in ${lane//+/ }; do
    [ -f "$p" ] || { echo "lanes: no plan file $p" >&2; exit 2; }
    while IFS= read -r line || [ -n "$line" ]; do
      body=${line%%#*}
      [[ "$body" =~ ^[[:space:]]*$ ]] && continue
      step=$(echo "${body%%:*}" | tr -d '[:space:]')
      grep -q "^$step:" "$plan.new" && continue
      echo "$step:${body#*:}" >> "$plan.new"
    done < "$p"
  done
  mv -f "$plan.new" "$plan"
  # its GPUs: an even share, or one shared round robin when there are fewer GPUs than lanes
  if [ "${#all[@]}" -ge "$nlanes" ]; then
    share=$(( ${#all[@]} / nlanes )) extra=$(( ${#all[@]} % nlanes ))
    first=$(( i * share + (i < extra ? i : extra) )) count=$(( share + (i < extra ? 1 : 0) ))
    mine=$(IFS=,; echo "${all[*]:$first:$count}")
  else
    mine=${all[$(( i % ${#all[@]} ))]}
  fi
  echo "lanes: $name on GPUs $mine: $lane"
  ( CUDA_VISIBLE_DEVICES=$mine QUEUE_STATE="$state/$name" OUT="$out/$name" \
      bash "$here/queue.sh" "$plan" > /dev/null 2>&1; echo $? > "$state/$name.rc" ) &
  pids+=($!)
  i=$((i + 1))
done
wait "${pids[@]}"
status=0
for j in $(seq 1 "$nlanes"); do
  rc=$(cat "$state/lane$j.rc" 2>/dev/null || echo 1)
  echo "lanes: lane$j's queue exit $rc; its last lines:"
  tail -4 "$out/lane$j/queue.log" 2>/dev/null | sed 's/^/  /'
  [ "$rc" = 0 ] || status=1
done
exit $status
