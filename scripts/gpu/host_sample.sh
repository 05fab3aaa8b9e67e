#!/usr/bin/env bash
# One sample of the host's memory, in MiB, as paper_study.sh takes it every half second while a stage runs:
#   used (MemTotal - MemAvailable: reclaimable page cache not counted), Shmem (files in a tmpfs are counted as used),
#   the machine's Python processes' anonymous resident memory summed (RssAnon: their own heap, not shared
#   libraries or file pages), how many Python processes there are (every one on the machine: the CLI's driver and
#   helpers with the stage's workers), and the MPS daemons' anonymous resident memory (server and control daemon).
# scripts/host_samples.py sums a stage's samples up.
awk '/^MemTotal:/{t=$2} /^MemAvailable:/{a=$2} /^Shmem:/{s=$2} END{printf "%d %d ", (t-a)/1024, s/1024}' /proc/meminfo
# Through cat: a process that exits between the glob and the read makes mawk (the GPU machine's awk) give up on
# the whole sample, where cat skips its file. Each status file starts with its Name line.
cat /proc/[0-9]*/status 2>/dev/null |
  awk '/^Name:/{n=$2} /^RssAnon:/{if (n ~ /^python/) {p+=$2; c++} else if (n ~ /mps/) m+=$2}
       END{printf "%d %d %d\n", p/1024, c, m/1024}'
