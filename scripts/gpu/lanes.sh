#!/usr/bin/env bash
# GPU: several plans at once on one machine of several GPUs, each in its own lane of the machine's GPUs:
#   bash scripts/gpu/lanes.sh PLAN_A PLAN_B+PLAN_C     (the same command in every call)
# An argument is one lane: plans joined by + run one after another in that lane (their steps, in order, as one
# queue). A step that a lane's earlier plan already has with the same command runs once; the same name with
# another command is refused (the queue keeps one state per name). The GPUs are split evenly between the lanes
# (the first lanes get the remainder; with fewer GPUs than lanes, lanes share them round robin; with none, every
# lane runs with CUDA_VISIBLE_DEVICES empty, a CPU dry run), pinned with CUDA_VISIBLE_DEVICES, so each plan sizes
# its render workers and trainings by its own GPUs. Each lane is a scripts/gpu/queue.sh with its own state
# (QUEUE_STATE/laneN) and output ($OUT/laneN/queue.log and queue.tgz: two of the device's eight files a lane),
# resumable across calls like one queue. Lanes must not share a run folder: their plans' RUN paths differ.
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

# Every lane's plan, merged and checked before any lane starts.
i=0
for lane in "$@"; do
  i=$((i + 1))
  plan="$state/lane$i.plan"
  : > "$plan.new"
  for p in ${lane//+/ }; do
    [ -f "$p" ] || { echo "lanes: no plan file $p (lane $i): no lane started" >&2; exit 2; }
    while IFS= read -r line || [ -n "$line" ]; do
      body=${line%%#*}
      [[ "$body" =~ ^[[:space:]]*$ ]] && continue
      body=${body%"${body##*[![:space:]]}"}        # trailing blanks (before a comment) are not the command
      step=$(echo "${body%%:*}" | tr -d '[:space:]')
      entry="$step:${body#*:}"
      before=$(awk -v s="$step" 'index($0, s ":") == 1' "$plan.new")
      if [ -n "$before" ]; then
        [ "$before" = "$entry" ] && continue
        echo "lanes: step '$step' of $p differs from the step of that name earlier in lane $i: rename one" \
             "(no lane started)" >&2
        exit 2
      fi
      echo "$entry" >> "$plan.new"
    done < "$p"
  done
  mv -f "$plan.new" "$plan"
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
  ( CUDA_VISIBLE_DEVICES=$mine QUEUE_STATE="$state/$name" OUT="$out/$name" \
      bash "$here/queue.sh" "$state/$name.plan" > /dev/null 2>&1; echo $? > "$state/$name.rc" ) &
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
