#!/usr/bin/env bash
# GPU: a session's plan, step after step, across the device's calls of at most 10 minutes.
#   bash scripts/gpu/queue.sh PLAN [PLAN...]  (the same command in every call: finished steps are skipped)
#   bash scripts/gpu/queue.sh --check PLAN [PLAN...]   (read the plans and say what is wrong; run nothing)
# PLAN has one step a line, "NAME: COMMAND" (bash; blank lines and # comments skipped). Every plan is read
# before any step runs. Several plans run one after another as one queue: a step that an earlier plan has too,
# with the same command, runs once; one name twice in a plan, or with two commands, is refused (exit 2). A step's command
# gets BUDGET (the seconds this call has left for it) and its own OUT folder, and must resume when called
# again. Its exit status says what happened:
#   0   done: never run again;
#   75  stopped for time (124/137: cut off by the budget, the same): the queue stops, the next call goes on
#       with this step;
#   any other: failed: recorded and left (its log says why), the queue goes on to the next step, so one
#       broken step does not cost a session. Remove QUEUE_STATE/NAME.failed to try it again.
# BUDGET seconds for the whole call (default 560, the device's 600 less the start and the transfers).
# $OUT gets queue.log (every step's output, written as it runs, so a call killed anyway still brings it back)
# and queue.tgz (every step's OUT folder, accumulated over the calls and packed after each step: the last
# call's tarball holds all), with queue-2.tgz for what queue.tgz cannot hold: at most three files of the
# device's eight.
set -uo pipefail
check=; [ "${1:-}" = --check ] && { check=1; shift; }
[ $# -ge 1 ] || { echo "usage: bash scripts/gpu/queue.sh [--check] PLAN [PLAN...]" >&2; exit 2; }
plans="$*"
BUDGET=${BUDGET:-560}
state=${QUEUE_STATE:-/tmp/queue}
out=${OUT:-/tmp/out}
[ -n "$check" ] || mkdir -p "$state/out" "$out"
t0=$(date +%s)
left() { echo $(( BUDGET - ($(date +%s) - t0) )); }
log=$out/queue.log
# The device brings back files of at most 16 MiB: above QUEUE_TGZ_BYTES the largest files (by their gzipped
# size) are left out of the tarball, and named in its LEFT_OUT.txt and the log, so that a large report does
# not cost the results beside it. Written to a temporary name and moved, so a call cut off while packing still
# brings back the previous tarball.
limit=${QUEUE_TGZ_BYTES:-15728640}
# What queue.tgz cannot hold goes into queue-2.tgz, as much as fits (largest first), unless QUEUE_OVERFLOW=0
# (scripts/gpu/lanes.sh turns it off for three lanes or more: the device brings back eight files a call). A
# study's eval brings its report and its per-clip predictions, ~10 MB each, beside its tables.
overflow=${QUEUE_OVERFLOW:-1}
# pack_overflow LEFT: of the files of LEFT (queue.tgz's left-out list), those that $out/queue-2.tgz.tmp holds, in
# $state/second.txt (empty, and no tarball, when none; pack moves the tarball into place after queue.tgz)
pack_overflow() {
  local tmp="$out/queue-2.tgz.tmp" chosen="$state/second.txt"
  rm -f "$tmp"; : > "$chosen"
  { [ "$overflow" != 0 ] && [ -s "$1" ]; } || return 0
  awk -v limit="$((limit - 65536))" -v skipfile="$1" 'BEGIN { while ((getline l < skipfile) > 0) left[l] = 1 }
    { p = substr($0, index($0, " ") + 1) } (p in left) && total + $1 <= limit { print p; total += $1 }' \
    "$state/gz_sizes.txt" > "$chosen"
  while [ -s "$chosen" ]; do
    # (names as they are: -T would otherwise read backslashes in them as escapes)
    if ! tar czf "$tmp" -C "$state/out" --no-wildcards --verbatim-files-from -T "$chosen" 2>/dev/null; then
      rm -f "$tmp"; : > "$chosen"; return 0        # a file gone or unreadable: nothing said to be in queue-2.tgz
    fi
    [ "$(stat -c %s "$tmp")" -le "$limit" ] && return 0
    sed -i 1d "$chosen"        # tar's overhead: the largest left out as well
  done
  rm -f "$tmp"
}
pack() {
  local left="$state/left_out.txt" tmp="$out/queue.tgz.tmp" sizes="$state/gz_sizes.txt" f
  rm -f "$state/out/LEFT_OUT.txt"
  # each file's gzipped size, largest first; leave out the largest until the rest fits
  ( cd "$state/out" && find . -type f -exec sh -c 'printf "%s %s\n" "$(gzip -c "$1" | wc -c)" "$1"' _ {} \; ) |
    sort -rn > "$sizes"
  awk -v limit="$((limit - 65536))" '{ n++; size[n] = $1; path[n] = substr($0, index($0, " ") + 1); total += $1 }
    END { for (i = 1; i <= n && total > limit; i++) { print path[i]; total -= size[i] } }' "$sizes" > "$left.new"
  while :; do
    pack_overflow "$left.new"
    if [ -s "$left.new" ]; then       # each file left out, and whether queue-2.tgz holds it
      awk -v secondfile="$state/second.txt" -v limit="$limit" -v overflow="$overflow" '
        BEGIN { while ((getline l < secondfile) > 0) two[l] = 1
                where = overflow != 0 ? "queue.tgz and queue-2.tgz" : "queue.tgz" }
        { print $0 (($0 in two) ? ": in queue-2.tgz (queue.tgz was full)" : ": left out of " where \
          " (the device brings back files of at most 16 MiB; limit " limit " bytes)") }' \
        "$left.new" > "$state/out/LEFT_OUT.txt"
    fi
    tar czf "$tmp" -C "$state/out" --no-wildcards -X "$left.new" . 2>/dev/null
    [ "$(stat -c %s "$tmp")" -le "$limit" ] && break
    # the estimate was short (tar's own overhead): leave out the next largest as well
    f=$(awk -v skipfile="$left.new" 'BEGIN { while ((getline l < skipfile) > 0) skip[l] = 1 }
             { p = substr($0, index($0, " ") + 1) } !(p in skip) { print p; exit }' "$sizes")
    [ -n "$f" ] || { echo "queue: queue.tgz is over $limit bytes with every file left out" | tee -a "$log"; break; }
    echo "$f" >> "$left.new"
  done
  mv -f "$tmp" "$out/queue.tgz"
  # the previous queue-2.tgz stays until this one replaces it (a call cut off while packing brings it back)
  if [ -s "$state/second.txt" ]; then mv -f "$out/queue-2.tgz.tmp" "$out/queue-2.tgz"; else rm -f "$out/queue-2.tgz"; fi
  [ -s "$left.new" ] && ! cmp -s "$left.new" "$left" && tee -a "$log" < "$state/out/LEFT_OUT.txt"
  mv -f "$left.new" "$left"
}
[ -n "$check" ] || trap pack EXIT
# Every plan read first, so that a bad step stops the queue before anything runs.
names=() cmds=() origins=()
refuse() { echo "queue: $*" | { [ -n "$check" ] && cat || tee -a "$log"; }; exit 2; }
for plan in "$@"; do
  [ -f "$plan" ] || refuse "no plan file $plan"
  seen=" "
  while IFS= read -r line || [ -n "$line" ]; do
    line=${line%%#*}
    [[ "$line" =~ ^[[:space:]]*$ ]] && continue
    line=${line%"${line##*[![:space:]]}"}     # trailing blanks (before a comment) are not the command
    [[ "$line" == *:* ]] || refuse "a line of $plan is not 'NAME: command' (is it a comment without its #?): $line"
    [[ "${line%%:*}" =~ ^[[:space:]]*[A-Za-z0-9_.-]+[[:space:]]*$ ]] ||
      refuse "bad step name '${line%%:*}' in $plan (one word before the colon; is it a comment without its #?)"
    name=${line%%:*}; name=${name//[[:space:]]/}
    cmd=${line#*:}
    [[ "$cmd" =~ [^[:space:]] ]] || refuse "step $name in $plan has no command"
    # A '#' inside a command starts a comment here (${f##*_} included), which can leave bash half a command.
    bash -n -c "$cmd" 2> /dev/null || refuse "step $name in $plan is not a whole bash command (bash cannot parse it; a '#' in a plan starts a comment, also inside \${...}): $cmd"
    [[ "$seen" == *" $name "* ]] && refuse "step $name twice in $plan"
    seen+="$name "
    for k in "${!names[@]}"; do
      [ "${names[$k]}" = "$name" ] || continue
      [ "${cmds[$k]}" = "$cmd" ] && continue 2      # an earlier plan's step, the same command: it runs once
      refuse "step '$name' of $plan differs from the step of that name in ${origins[$k]}: rename one"
    done
    names+=("$name") cmds+=("$cmd") origins+=("$plan")
  done < "$plan"
done
[ -n "$check" ] && exit 0
for k in "${!names[@]}"; do
  name=${names[$k]} cmd=${cmds[$k]}
  if [ -f "$state/$name.done" ]; then echo "== $name: done before" | tee -a "$log"; continue; fi
  if [ -f "$state/$name.failed" ]; then echo "== $name: failed before, left" | tee -a "$log"; continue; fi
  budget=$(( $(left) - 15 ))                  # the tarball's time
  [ "$budget" -gt 30 ] || { echo "== $name: no time left in this call: call again" | tee -a "$log"; exit 0; }
  echo "== $name ($budget s left): $cmd" | tee -a "$log"
  mkdir -p "$state/out/$name"
  s0=$(date +%s)
  BUDGET=$budget OUT="$state/out/$name" timeout -k 10 "$budget" bash -c "$cmd" < /dev/null 2>&1 | tee -a "$log"
  rc=${PIPESTATUS[0]}
  echo "== $name: exit $rc after $(( $(date +%s) - s0 )) s" | tee -a "$log"
  pack                                        # so a call the device cuts off still brings the finished steps
  case $rc in
    0) touch "$state/$name.done" ;;
    75|124|137) echo "queue: $name goes on in the next call" | tee -a "$log"; exit 0 ;;
    *) echo "$rc" > "$state/$name.failed" ;;
  esac
done
echo "queue: every step of $plans has run ($(ls "$state"/*.failed 2>/dev/null | wc -l) failed)" | tee -a "$log"
