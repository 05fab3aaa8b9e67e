#!/usr/bin/env bash
# GPU: several commands at once, e.g. two settings' data, whose host work (the render's is most of it at
# 112 px) overlaps on one machine:
#   bash scripts/gpu/together.sh "RUN=/tmp/wind DATA_ONLY=1 bash scripts/gpu/more_data.sh" \
#                                "RUN=/tmp/arm MOTIONS=arm DATA_ONLY=1 bash scripts/gpu/more_data.sh"
# Each command's output lines are prefixed with its number. Exit status in queue.sh's terms: 0 when every
# command exited 0; 1 when one failed (any status but 0, 75, 124, 137); else 75 (one stopped for time).
set -uo pipefail
[ $# -ge 1 ] || { echo "usage: bash scripts/gpu/together.sh CMD [CMD...]" >&2; exit 2; }
tmp=$(mktemp -d)
i=0
for cmd in "$@"; do
  i=$((i + 1))
  ( bash -c "$cmd" < /dev/null 2>&1 | sed -u "s/^/[$i] /"; echo "${PIPESTATUS[0]}" > "$tmp/$i" ) &
done
wait
worst=0
for j in $(seq 1 $i); do
  rc=$(cat "$tmp/$j" 2>/dev/null || echo 1)
  echo "together: command $j exit $rc"
  case $rc in
    0) ;;
    75|124|137) [ $worst = 1 ] || worst=75 ;;
    *) worst=1 ;;
  esac
done
rm -rf "$tmp"
exit $worst
